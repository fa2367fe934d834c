#!/usr/bin/env python3
"""Run the ``vcan``-marked hardware-in-the-loop tests against a real SocketCAN vcan0.

Why this exists: the HIL tests need kernel SocketCAN, but the development and CI
machines run kernels without CAN (socket(AF_CAN) fails with errno 97). This finds a
kernel with vcan, by probing, in this order (``--way auto``): the host's own;
user-mode Linux from Debian testing, fetched through a private apt list into
``${XDG_CACHE_HOME:-~/.cache}/dbw-applique/vcan/``, if a probe boot brings vcan0 up (its
seccomp mode halves the cost of the guest's system calls: tools/vcan/ways.py); the
system's user-mode Linux (``/usr/bin/linux.uml``), probed the same way (bookworm's panics
at init on CPUs with AMX); QEMU with bookworm's kernel. A guest sees the host's root
file system, so it runs this very checkout and virtualenv; the test output and exit
status come back through files on the host. The machinery is in ``tools/vcan/``; the recipes are in
/work/shared/notes/vcan-on-amx-hosts.md and vcan-without-kernel-support.md.

Usage: tools/vcan_run.py [--way auto|native|uml-system|uml-testing|qemu] [--timeout-s N]
       [pytest args...]
Unknown arguments (or everything after ``--``) go to pytest. ``-m vcan`` is added
unless a ``-m`` is given, because pyproject's addopts deselect vcan tests by default
(a later ``-m`` on the command line wins over addopts). When no way works it says, in
one line, what it tried and why each failed, and exits 125: it never skips.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tools.vcan.common import DEFAULT_PYTEST_ARGS, EXIT_RUNNER_FAILURE, log, pytest_command
from tools.vcan.ways import WAYS, NoWay, cache_dir, finders, order_for, select


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    after_dashes = argv[argv.index("--") + 1 :] if "--" in argv else []
    ours = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        epilog=f"Other arguments, and all after --, go to pytest (default: "
        f"{' '.join(DEFAULT_PYTEST_ARGS)}); -m vcan is added unless a -m is given.",
        allow_abbrev=False,
    )
    parser.add_argument(
        "--way",
        choices=("auto", *WAYS),
        default="auto",
        help="auto (default): the first of " + ", ".join(WAYS) + " whose probe passes",
    )
    parser.add_argument("--timeout-s", type=float, default=600.0, help="pytest's limit (600)")
    parser.add_argument("--mem", default="1G", help="the guest's memory (1G)")
    opts, pytest_args = parser.parse_known_args(ours)
    cmd = pytest_command(os.path.abspath(sys.executable), pytest_args + after_dashes)
    start = time.monotonic()
    try:
        kernel = select(order_for(opts.way), finders(opts.mem, cache_dir()))
    except NoWay as exc:
        print(exc, file=sys.stderr, flush=True)
        return EXIT_RUNNER_FAILURE
    log(f"{kernel.description}{'; ' + kernel.slow_note if kernel.slow_note else ''}")
    log(f"kernel ready after {time.monotonic() - start:.1f} s; running pytest")
    rc = kernel.run(cmd, opts.timeout_s)
    print(
        f"vcan_run: exit status {rc} after {time.monotonic() - start:.1f} s ({kernel.way})",
        flush=True,
    )
    return rc


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # a running guest has already been killed
        print("vcan_run: interrupted", file=sys.stderr)
        sys.exit(130)
