from __future__ import annotations

import pytest

from lfstudy.optics import PlenopticCamera


@pytest.fixture
def table41_camera() -> PlenopticCamera:
    """The 1-D simulator camera of Table 4.1 (fm = 1.5 mm, M = -1)."""
    return PlenopticCamera(75, 75, 0.0074, 0.125, 0.5, 1.5, -1.0)


@pytest.fixture
def table43_camera() -> PlenopticCamera:
    """The KAI-16000 camera of Table 4.3."""
    return PlenopticCamera(4872, 3248, 0.0074, 0.125, 0.5, 50.0, -1.0)
