"""The shipped instrument models agree with the device description they claim to be."""

import numpy as np
import pytest
from pydrake.geometry import Cylinder, Role, Sphere
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.hardware import default_instrument
from maglev_haptics.plant_models import PACKAGE_XML


def load(kind):
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 1e-3)
    parser = Parser(plant)
    parser.package_map().AddPackageXml(str(PACKAGE_XML))
    instance = parser.AddModels(url=default_instrument(kind).model_url)[0]
    plant.Finalize()
    return plant, scene_graph, instance


@pytest.mark.parametrize("kind", ["two_magnet", "four_magnet"])
def test_mass_inertia_markers_and_magnets_match_the_spec(kind):
    spec = default_instrument(kind)
    plant, scene_graph, instance = load(kind)
    body = plant.GetBodyByName("instrument", instance)
    inertia = body.default_spatial_inertia()
    assert inertia.get_mass() == pytest.approx(spec.mass_kg, rel=1e-6)
    np.testing.assert_allclose(inertia.get_com(), 0.0, atol=1e-12)
    np.testing.assert_allclose(inertia.CalcRotationalInertia().CopyToFullMatrix3(),
                               spec.inertia_about_I(), rtol=1e-5, atol=1e-12)
    for k, p_IK in enumerate(spec.p_IK):
        frame = plant.GetFrameByName(f"marker_{k}", instance)
        np.testing.assert_allclose(frame.GetFixedPoseInBodyFrame().translation(), p_IK, atol=1e-9)

    inspector = scene_graph.model_inspector()
    frame_id = plant.GetBodyFrameIdOrThrow(body.index())
    magnets = []
    for geometry in inspector.GetGeometries(frame_id, Role.kIllustration):
        name = inspector.GetName(geometry).split("::")[-1]
        if name.startswith("magnet_") and not name.endswith("_north"):
            shape = inspector.GetShape(geometry)
            assert isinstance(shape, Cylinder)
            assert shape.radius() == pytest.approx(spec.magnet.diameter_m / 2)
            assert shape.length() == pytest.approx(spec.magnet.height_m)
            magnets.append(inspector.GetPoseInFrame(geometry).translation())
    np.testing.assert_allclose(sorted(map(tuple, magnets)), sorted(map(tuple, spec.p_IM)),
                               atol=1e-9)

    # The lowest collision point is the base's underside: the instrument rests at rest_height_m.
    lowest = min(inspector.GetPoseInFrame(g).translation()[2] - inspector.GetShape(g).radius()
                 for g in inspector.GetGeometries(frame_id, Role.kProximity)
                 if isinstance(inspector.GetShape(g), Sphere))
    assert -lowest == pytest.approx(spec.rest_height_m, abs=1e-9)
