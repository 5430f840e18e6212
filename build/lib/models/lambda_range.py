"""The range of λ, the asymmetric loss weight (Vogels et al. 2018, eq. 6): training draws
log λ ~ U(0, log 10), so the network knows λ in [1, 10] and nothing outside it. No torch here,
so the job spec and the CLI can import it cheaply."""

LAMBDA_MIN, LAMBDA_MAX = 1.0, 10.0
