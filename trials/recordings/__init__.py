"""Recordings as input (``advobj record import``): this project's trial sessions and LeRobot datasets
read into the one recording format (:mod:`sim.recording`)."""
