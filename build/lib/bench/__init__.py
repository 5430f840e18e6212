"""The measurement wing: benchmarks and reports (never imported by the product)."""
