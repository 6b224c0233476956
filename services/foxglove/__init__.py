"""The bus live in Foxglove: a Foxglove WebSocket server (foxglove-sdk) fed from zenoh."""
