"""Process supervision and live runs: the ready handshake, v2i demo, the site demo, the ROIF demo, replay scoring."""
