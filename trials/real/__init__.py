"""Real-robot trials (issue 8): the trial plan, the trial store and runner, and the reports.

Top floor: may import ``sim``, ``calibration``, ``attack`` and ``robot_io``; nothing imports it.
"""
