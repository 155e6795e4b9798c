"""The scene's table half-space stays out of deformable contact: building a haptic
scene and its context prints no Drake warning about it."""

import logging

import pytest
from pydrake.geometry import HalfSpace
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.diagrams.scene import HangingBall, PaddleBall, PegInHole
from maglev_haptics.diagrams.scene_builder import AddScene

HOVER = RigidTransform([0.0, 0.0, 0.06])  # instrument start, clear of every scene (m)
HALF_SPACE_WARNING = "half spaces are not currently supported for deformable contact"


@pytest.mark.parametrize("scene", [PegInHole(), HangingBall(), PaddleBall()],
                         ids=lambda scene: type(scene).__name__)
def test_building_a_scene_with_a_table_prints_no_half_space_warning(scene, capfd, caplog):
    builder = DiagramBuilder()
    parts = AddScene(builder, scene=scene, time_step_s=1e-3, X_WI_start=HOVER)
    diagram = builder.Build()
    with caplog.at_level(logging.WARNING, logger="drake"):
        context = diagram.CreateDefaultContext()  # where SceneGraph fills in its defaults
    captured = capfd.readouterr()
    for text in (captured.out, captured.err, caplog.text):
        assert HALF_SPACE_WARNING not in text

    # Drake warns once a process, so also check the cause: a half-space with a resolution
    # hint is what enrols it for deformable contact.
    scene_graph_context = parts.scene_graph.GetMyContextFromRoot(context)
    inspector = parts.scene_graph.get_query_output_port().Eval(scene_graph_context).inspector()
    tables = [geometry for geometry in inspector.GetAllGeometryIds()
              if isinstance(inspector.GetShape(geometry), HalfSpace)]
    assert len(tables) == 1
    properties = inspector.GetProximityProperties(tables[0])
    assert not properties.HasProperty("hydroelastic", "resolution_hint")
