"""Fixtures for the estimator tests: robots and estimator models."""
from __future__ import annotations

import pytest

import robot_description
from estimator_truth import ROBOTS
from gateway.estimator import EstimatorModel


@pytest.fixture(scope="module", params=ROBOTS)
def robot(request):
    return robot_description.load(request.param)


@pytest.fixture(scope="module")
def emodel(robot):
    return EstimatorModel.from_robot(robot)
