"""SRD-Bench: joint super-resolution and denoising of Monte Carlo renders, benchmarked."""
