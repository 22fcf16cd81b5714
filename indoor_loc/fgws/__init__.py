"""The Foxglove WebSocket protocol (v1) served without the Foxglove SDK: both subprotocol names, two-way."""
