"""The steps a user runs, each in memory with a result that ``save`` writes: calibrate, diagnose, uncertainty, compare, a fleet."""
