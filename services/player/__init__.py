"""``wavegrasp player``: replays a recording (MCAP, ROS 1 bag, ROS 2 bag) over the bus."""
