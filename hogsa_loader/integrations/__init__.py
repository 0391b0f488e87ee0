"""Drop-in integrations of the synthetic loader into existing training code."""
