"""The PyBullet simulator that executes approved plans and judges each grasp."""
