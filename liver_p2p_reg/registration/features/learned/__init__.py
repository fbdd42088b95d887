"""The learned point matcher: its network, descriptors, weights (safetensors) and feature provider."""
