"""wavegrasp: motion-aware underwater grasping over Eclipse Zenoh."""
