"""``wavegrasp recorder``: every message on the bus into ``run.mcap``, with a schema per channel."""
