"""Perception: what the scans show, as features in the vehicle frame.

Home of Qian et al.'s scan processing (section 3.2: segments and the launcher's boards and
cylinders from both LMS111s) and of Kinouchi et al.'s pallet detection in scans and in a
worker's point cloud (section 2.2 (2)). Pure: arrays in, features out, no asyncio, no I/O,
time as an argument; it imports the drivers' data types (``drivers.lms111.mounted``) and
numpy, and nothing of the runtime (the import contracts in pyproject.toml say so).

The scan path, one module per step: ``points`` (polar beams to the output frame),
``segments`` (adaptive breakpoints), ``lines`` (split-and-merge) with ``line_fit`` (the
weighted TLS line and its covariance), ``circles`` (circle fits and their covariance,
their least-squares search in ``circle_search``) with ``cylinders`` (when an arc is the
landmark), and ``features`` (the whole scan, with regions of interest). ``types`` holds
what comes out (`ScanFeatures`, `LineFeature`, `CircleFeature`, `FitRejection`) and what
the fits assume of the scanner (`ScannerModel`); ``gates`` the χ² quantile the tests
share. ``jit`` compiles, at import, the loops numpy cannot make cheap on a few dozen points:
``circle_search`` (the circle fits' search, covariance and trimmed arc) and
``line_kernels`` (the weighted line's iterations, split-and-merge and its corners).
"""
