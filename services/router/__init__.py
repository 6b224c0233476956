"""``wavegrasp router``: the zenoh router every service connects to (there is no zenohd on PyPI)."""
