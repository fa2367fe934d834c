"""The pure control core: one ``step`` per cycle, explicit time, no I/O.

``ControlCore.step(inputs, now_s)`` takes the latest value of every input with its age
and returns every command of the cycle; the control loop (``appliance/control_loop.py``)
is the only thing that touches topics and drivers. The same core runs in the daemon, in
faster-than-real-time tests and in replay.
"""
