"""The jaxafm version, written into every model file and run manifest (a leaf: any layer may
import it)."""

__version__ = "0.1.0"
