"""Calibration maneuvers and their fits: pure numpy, no I/O, no clock, no asyncio.

What a technician measures once per kit installation becomes numbers here (the pot map's
polynomial today; pot centre, palm tree, k ratio, look-ahead and pedal sweeps next). The
versioned file those numbers are written to is part of the vehicle's configuration
(``appliance.config.calibration``, ``appliance.config.calibration_file``), and running a
maneuver against the daemon is the command line's job; both sit above this package.
"""
