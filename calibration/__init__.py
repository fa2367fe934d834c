"""Calibration maneuvers and their fits: numpy and scipy, no I/O, no clock, no asyncio.

What a technician measures once per kit installation becomes numbers here: the pot
centre, the pot map and its backlash, the throttle and brake maps, the palm tree's wheel
to tyre map, the counter-steer ratio k, the look-ahead schedule and the servo-torque
check. Each fit takes arrays and returns a frozen result: the values, the method, the
residuals, every refused sample counted by reason, and a verdict against stated
thresholds; samples may also stream in through a small accumulator. The
versioned file those numbers are written to is part of the vehicle's configuration
(``appliance.config.calibration``, ``appliance.config.calibration_file``), and running a
maneuver against the daemon is the command line's job; both sit above this package.
"""
