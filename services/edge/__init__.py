"""The vehicle's edge stage: the camera's clouds cut down to what the tether can carry."""
