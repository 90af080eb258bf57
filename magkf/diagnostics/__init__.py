"""Compare the model with the measurements: ``diagnose`` (residuals against every signal, which physical
effect is missing) and ``report`` (one self-contained HTML file with the plots)."""
