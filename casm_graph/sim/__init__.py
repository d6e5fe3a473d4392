"""Simulated logs with known truth: the Aibo field, SCASM's 1-D walk and a wheeled robot's floor."""
