"""What a fitted model says: residuals, the diagnosis of missing effects, uncertainty, comparisons."""
