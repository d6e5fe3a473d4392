"""The seed papers' other methods: SCASM's 1-D calibration and MCL with dynamic motion models."""
