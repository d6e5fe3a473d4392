"""The factor graph of a log: variables, factor rows and Jacobians, and the sparse elimination kernel."""
