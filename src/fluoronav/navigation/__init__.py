"""fluoronav.navigation."""
