"""Benchmark harness: runs registration methods on test cases and writes tables, curves and statistics."""
