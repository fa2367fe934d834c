"""dbw-applique: the drive-by-wire appliqué runtime (daemon, control core, config)."""

__version__ = "0.1.0"
