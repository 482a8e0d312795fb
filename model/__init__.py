"""texspace model package."""
