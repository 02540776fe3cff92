"""motok: learned human motion, from mocap to tokens, text and physics."""

__version__ = "0.1.0"
