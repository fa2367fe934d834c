"""A click group whose subcommands are imported only when one of them is run.

Why: every `dbw` command used to import every other one first. The calibration steps
pull in the replay of recordings and with it the whole control core, the pallet planner
and scipy; `dbw status` on the vehicle PC took 2.5 s before it asked the daemon anything,
and so did the simulated vehicle's process (`dbw sim`) each time the daemon started it;
`dbw --help` took 2.5 s, importing every command to list it (now 0.25 s on the same
machine: `dbw run` is lazy too, and the vehicle file's models are not imported for it).
Here a subcommand is named with where it lives ("module:attribute") and imported when
click asks for it: to run it, or to list it in ``--help`` unless the group was given its
summary (the line ``--help`` shows; a test holds each to the command's own).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

import click


class LazyGroup(click.Group):
    """`click.Group` with ``lazy_subcommands``: name to ``"package.module:attribute"``,
    and ``summaries``: name to the short help ``--help`` lists it with."""

    def __init__(
        self,
        *args: Any,
        lazy_subcommands: Mapping[str, str] | None = None,
        summaries: Mapping[str, str] | None = None,
        **kwargs: Any,
    ):
        super().__init__(*args, **kwargs)
        self.lazy_subcommands = dict(lazy_subcommands or {})
        self.summaries = dict(summaries or {})

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *self.lazy_subcommands})

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name in self.lazy_subcommands:
            return self._load(cmd_name)
        return super().get_command(ctx, cmd_name)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """click's list of commands, where a lazy command with a summary is not imported
        (a stand-in carrying the summary is asked for its short help instead)."""
        rows: list[tuple[str, click.Command]] = []
        for name in self.list_commands(ctx):
            if name in self.lazy_subcommands and name in self.summaries:
                rows.append((name, click.Command(name, help=self.summaries[name])))
            elif (command := self.get_command(ctx, name)) is not None and not command.hidden:
                rows.append((name, command))
        if not rows:
            return
        limit = formatter.width - 6 - max(len(name) for name, _ in rows)
        with formatter.section("Commands"):
            formatter.write_dl(
                [(name, command.get_short_help_str(limit)) for name, command in rows]
            )

    def _load(self, cmd_name: str) -> click.Command:
        """Import the command; a wrong name here is a bug of this package, said as such."""
        module_name, _, attribute = self.lazy_subcommands[cmd_name].partition(":")
        command = getattr(importlib.import_module(module_name), attribute)
        if not isinstance(command, click.Command):
            raise TypeError(f"{module_name}:{attribute} is not a click command (for {cmd_name})")
        return command
