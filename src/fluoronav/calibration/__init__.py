"""fluoronav.calibration."""
