"""The simulated devices, wired to the simulated world.

Each twin speaks its device's protocol through the device model its driver folder keeps
(``drivers.lms111.twin_device``, ``drivers.actuators.twin``) or through the protocol core
itself (the PC104's DBC codec), and sees the world through ``appliance.sim``: the scanners
render the site from the vehicle's pose, the boards and the PC104 move the simulated
vehicle. The device folders below know nothing of the world; this package is the glue.
"""
