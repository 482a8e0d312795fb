"""texspace service package."""
