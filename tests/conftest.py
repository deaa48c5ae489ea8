"""Test-session settings shared by unit and integration tests."""

from hypothesis import HealthCheck, settings

# CI machines are small and noisy: no per-example deadline.
settings.register_profile("co3sop", deadline=None, max_examples=60, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("co3sop")
