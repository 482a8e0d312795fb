"""texspace worker package."""
