"""Experiment scripts (run each as ``python experiments/<name>.py``), importable for the tests."""
