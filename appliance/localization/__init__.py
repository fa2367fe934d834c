"""Localization: where the vehicle is, and where the things it looks for are.

Home of the launcher-pose estimate and its EKF (Qian et al., eqs. 1-10), the GNSS/INS
fix in a local east-north frame (Stanley et al.), and the merging of a worker's pallet map
into the vehicle's (Kinouchi et al., eq. 2). Pure, like perception below it: features and
fixes in, poses with covariance out, time as an argument, small classes with
``reset()``/``update()``.
"""
