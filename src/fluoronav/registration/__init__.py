"""fluoronav.registration."""
