"""The scene as Foxglove and rviz2 draw it: /tf, robot_description and markers."""
