"""Training the matcher: the training loop, its validation, and patient preparation (fine-tuning on one preop model)."""
