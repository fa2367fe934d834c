"""Guidance: where the vehicle should go next, as a wish the core may refuse.

Home of routes, four-wheel-counter-steer pure pursuit and speed by throttle and brake
(Stanley et al., eqs. 1-3), the flat-bed's docking patterns (Qian et al., 4.1-4.3) and the
forklift's approach into the blind area (Kinouchi et al., 3.1-3.2). Each is an autopilot
source (``appliance.core.autopilot``): it returns a steering and speed wish from the
cycle's observation, and the mode machine and the safety layer decide what of it is sent.
Pure, and below the core: it may use localization and perception, never the runtime.
"""
