"""fluoronav.simulation."""
