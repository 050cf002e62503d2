"""Inference engines over driver-model parameters and their shared result layout."""
