"""The CLI accepts the v1 tier ids wherever it accepts an env id."""

from __future__ import annotations

import pytest

import auv_follow_env
from agents.cli import build_parser


@pytest.mark.parametrize("env_id", auv_follow_env.ENV_IDS_V1)
def test_train_evaluate_compare_accept_v1_ids(env_id):
    p = build_parser()
    assert p.parse_args(["train", "--env", env_id]).env_id == env_id
    assert p.parse_args(["evaluate", "run", "--env", env_id]).env_id == env_id
    assert p.parse_args(["compare", "--env", env_id]).env_id == env_id
