import pytest


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: takes more than about a minute on one CPU core (still part of make test)")
