"""Safety layer: what stands between the control core and the actuators and cannot be bypassed."""
