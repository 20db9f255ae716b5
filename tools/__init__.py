"""satpose.tools."""
