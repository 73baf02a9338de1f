"""fluoronav.studies."""
