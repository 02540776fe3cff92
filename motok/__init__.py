"""motok: learned human motion, from mocap to tokens, text and physics."""

__version__ = "0.2.0"
