"""Calibration for real trials: camera intrinsics (ChArUco), AprilTag object poses, eye-in-hand
``T_tcp_cam``, the frame chain base <- tcp <- cam <- tag <- object, and the real-world reach outcome.

Modules: ``intrinsics`` (board, calibration, camera YAML), ``apriltag`` (detection, both IPPE
solutions, ambiguity, bundles), ``registry`` (tag id -> object), ``handeye``, ``frames``,
``outcome`` (reach criterion with *unknown*), ``printables`` (true-scale PDFs), ``synthetic``
(OpenGL renders with known ground truth), ``selfcheck``, ``io`` and ``errors``.
Ground floor: imports ``sim.geometry``, ``sim.outcome`` and ``sim.errors`` only.
"""
