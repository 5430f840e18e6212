"""Training the networks from a rendered data set (`renderloop train`)."""
