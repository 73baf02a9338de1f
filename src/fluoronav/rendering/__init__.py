"""fluoronav.rendering."""
