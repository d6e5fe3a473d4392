"""Getting the graph to its optimum: initialisation, the methods, noise levels, and the calibration result."""
