"""The vehicle PC itself as a device: load, memory, disk, temperature, clocks."""
