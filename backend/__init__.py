"""satpose.backend."""
