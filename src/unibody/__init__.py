"""unibody: one canonical body for every parametric human model."""
