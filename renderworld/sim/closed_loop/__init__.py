"""Closed-loop driving in the simulator: a planner drives, the scene answers, scores say how."""
