"""Inference: parameter space and priors, likelihood, MAP search, emcee sampling, results."""
