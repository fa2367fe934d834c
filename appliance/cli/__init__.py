"""`dbw`: the one command a person uses on the vehicle and on the bench.

One module per command group: ``main`` (the group), ``run`` (the daemon), ``config``,
``calibration``, ``control`` (``dbw status``, ``engage``, ``hold``, ...; ``status_view``
renders the status), ``lms111`` and ``sim``; ``common`` holds what they share. Errors a
person can fix (a bad config file) are printed as plain sentences with exit status 2;
tracebacks are for bugs only.
"""

from appliance.cli.main import cli, main

__all__ = ["cli", "main"]
