"""``wavegrasp planner``: a grasp at the predicted position and a timed approach to it."""
