"""The report tests' figures are closed after each test (pyplot keeps every open figure)."""

from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def close_figures() -> Iterator[None]:
    yield
    import matplotlib.pyplot as plt  # here, not at the top: every pytest-xdist worker collects this folder

    plt.close("all")
