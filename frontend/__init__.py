"""satpose.frontend."""
