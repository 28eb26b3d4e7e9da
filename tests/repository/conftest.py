"""Every test here checks the repository around the package (docs, notebooks, benchmarks,
validation scripts, the layer rule): marked ``integration``. The default run includes them;
``pytest -m "not integration"`` runs the package's own tests alone."""

import pytest


def pytest_collection_modifyitems(items):
    for item in items:
        if "/repository/" in str(item.path):
            item.add_marker(pytest.mark.integration)
