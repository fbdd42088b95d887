"""Learned rotation-invariant point matcher: invariant descriptors, network, weights, training, pipelines."""
