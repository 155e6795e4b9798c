"""Fixtures shared by the test modules."""

import pytest
from pydrake.geometry import Meshcat, MeshcatParams

from maglev_haptics.diagrams.meshcat_lifetime import close_meshcat, start_meshcat


def _msgpack_str(text: str) -> bytes:
    data = text.encode()
    assert len(data) < 32  # a msgpack fixstr
    return bytes([0xA0 | len(data)]) + data


def _click(meshcat: Meshcat, name: str) -> None:
    """What a browser sends when a button is clicked: {"type": "button", "name": name}."""
    meshcat._InjectWebsocketMessage(message=bytes([0x82]) + _msgpack_str("type")
                                    + _msgpack_str("button") + _msgpack_str("name")
                                    + _msgpack_str(name))


@pytest.fixture(scope="module")
def meshcat():
    """A Meshcat on 127.0.0.1 for a test module, closed on this thread when the module ends."""
    viewer = start_meshcat(MeshcatParams(host="127.0.0.1"))
    yield viewer
    close_meshcat(viewer)


@pytest.fixture
def click_button():
    """click_button(meshcat, name): press a Meshcat button as the browser would."""
    return _click
