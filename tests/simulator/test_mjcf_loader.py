"""The MJCF reader refuses what it does not model, naming the element, the attribute and the file."""
import pytest

from torchrl_diffenvs.articulated import MJCFError, load_mjcf

BODY = '<geom type="sphere" size="0.1"/>'


def _model(tmp_path, worldbody: str, extra: str = ""):
    path = tmp_path / "model.xml"
    path.write_text(f"<mujoco><worldbody>{worldbody}</worldbody>{extra}</mujoco>")
    return path


@pytest.mark.parametrize("worldbody,extra,message", [
    (f'<body><joint type="ball" limited="true" range="0 30"/>{BODY}</body>', "",
     "limits on a ball joint are not supported"),
    (f'<body><joint type="ball" stiffness="2"/>{BODY}</body>', "", "stiffness on a ball joint is not supported"),
    (f'<body>{BODY}<body><freejoint/>{BODY}</body></body>', "",
     "a free joint must belong to a child of the world body"),
    (f'<body><joint type="ball"/><joint type="hinge"/>{BODY}</body>', "", "a ball joint must be the last joint"),
    (f'<body><freejoint align="true"/>{BODY}</body>', "", "attribute 'align' is not supported"),
    (f'<body><joint name="j" type="free"/>{BODY}</body>', '<actuator><motor joint="j"/></actuator>',
     "motors on ball and free joints are not supported"),
    (f'<body><joint type="universal"/>{BODY}</body>', "", "supported: hinge, slide, ball, free"),
    (f'<body><joint frictionloss="1"/>{BODY}</body>', "", "frictionloss"),
    (f"<body><joint/>{BODY}</body>", "<tendon><spatial/></tendon>", "tendon type not supported"),
])
def test_unsupported_model_parts_raise_naming_them_and_the_file(tmp_path, worldbody, extra, message):
    path = _model(tmp_path, worldbody, extra)
    with pytest.raises(MJCFError, match=message) as error:
        load_mjcf(path)
    assert str(path) in str(error.value)


def test_free_and_ball_joints_number_coordinates_and_dofs_as_mujoco(tmp_path):
    """A free joint takes 7 coordinates and 6 dofs, a ball 4 and 3, a hinge 1 and 1 (MuJoCo's
    numbering); the free joint starts at its body's file pose and carries no damping (``<freejoint>``)."""
    path = _model(tmp_path, f'<body pos="1 2 3" euler="0 0 90"><freejoint/>{BODY}'
                            f'<body><joint type="ball" damping="0.5"/>{BODY}'
                            f'<body><joint type="hinge" ref="10"/>{BODY}</body></body></body>')
    model = load_mjcf(path)
    assert (model.nq, model.nv, model.njnt) == (12, 10, 3)
    assert model.joint_qposadr.tolist() == [0, 7, 11] and model.joint_dofadr.tolist() == [0, 6, 9]
    assert model.dof_joint.tolist() == [0] * 6 + [1] * 3 + [2]
    assert model.qpos0[:3].tolist() == [1.0, 2.0, 3.0]
    assert model.qpos0[3:7] == pytest.approx([2 ** -0.5, 0.0, 0.0, 2 ** -0.5])  # 90 degrees about z
    assert model.qpos0[7:].tolist() == pytest.approx([1.0, 0.0, 0.0, 0.0, 10 * 3.141592653589793 / 180])
    assert model.damping.tolist() == [0.0] * 6 + [0.5] * 3 + [0.0]
