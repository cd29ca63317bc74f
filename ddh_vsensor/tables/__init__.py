"""Movement tables: built from the steady state, stored versioned, looked up by the estimator."""
