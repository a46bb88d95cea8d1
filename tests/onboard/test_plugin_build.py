"""Building a plug-in (onboard.pipeline.plugins.build): a factory that raises is one configuration error line."""

from __future__ import annotations

import pytest

from onboard.app.config import OnboardConfig
from onboard.core.errors import ConfigError
from onboard.pipeline.plugins import TRACKERS, build


class InitRaises:
    def __init__(self, config):
        raise RuntimeError("boom in __init__")


class InitExits:
    def __init__(self, config):
        raise SystemExit(3)


class ImportsMissing:
    def __init__(self, config):
        import irtrack_no_such_module  # noqa: F401


@pytest.mark.parametrize(
    "attr, group, option, message",
    [
        ("InitRaises", TRACKERS, "--tracker", "RuntimeError: boom in __init__"),
        ("ImportsMissing", None, "algorithms", "ModuleNotFoundError: No module named 'irtrack_no_such_module'"),
        ("InitExits", None, "--estimator", "SystemExit: 3"),
    ],
)
def test_a_plug_in_whose_construction_raises_is_a_config_error_naming_the_option_and_the_plug_in(
    attr, group, option, message
):
    name = f"{__name__}:{attr}"
    kw = {"option": option} if group is None else {"group": group, "option": option}
    with pytest.raises(ConfigError) as info:
        build(name, OnboardConfig(), **kw)
    assert str(info.value) == f"{option} {name}: {message}"


def test_a_factory_s_own_config_error_goes_out_as_it_is():
    import dataclasses

    config = OnboardConfig()
    off = dataclasses.replace(config, estimator=dataclasses.replace(config.estimator, enabled=False))
    with pytest.raises(ConfigError, match=r"^--estimator map: the configuration's estimator.enabled is false$"):
        build("map", off)
