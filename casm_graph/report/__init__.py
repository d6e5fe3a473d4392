"""The HTML pages of calibrations, diagnoses and posteriors, figures embedded."""
