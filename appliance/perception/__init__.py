"""Perception: what the scans show, as features in the vehicle frame.

Home of Qian et al.'s scan processing (section 3.2: segments and the launcher's boards and
cylinders from both LMS111s) and of Kinouchi et al.'s pallet detection in scans and in a
worker's point cloud (section 2.2 (2)). Pure: arrays in, features out, no asyncio, no I/O,
time as an argument; it imports the drivers' data types (``drivers.lms111.mounted``) and
numpy, and nothing of the runtime (the import contracts in pyproject.toml say so).
"""
