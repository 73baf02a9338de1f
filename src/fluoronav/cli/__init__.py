"""fluoronav.cli."""
