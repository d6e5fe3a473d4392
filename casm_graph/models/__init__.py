"""What is calibrated: the model (action table or command map, sensor curve, noise) and the effect catalog."""
