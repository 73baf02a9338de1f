"""fluoronav.detection."""
