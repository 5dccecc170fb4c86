"""Example pointflow transport plugin."""
from .helix import HelixTransport

__all__ = ["HelixTransport"]
