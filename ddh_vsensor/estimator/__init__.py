"""The position estimator: one integrator with an online and an offline face."""
