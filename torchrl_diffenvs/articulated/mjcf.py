"""An MJCF reader for the subset of MuJoCo's XML that Gymnasium's own model files use.

[`load_mjcf`][torchrl_diffenvs.articulated.load_mjcf] turns a model file into an [`ArticulatedModel`][torchrl_diffenvs.articulated.ArticulatedModel]: plain float64 numpy arrays
(bodies, joints, geoms, motors) that `torchrl_diffenvs.articulated.dynamics` turns into
tensors. It follows MuJoCo's compiler where it matters for the dynamics:

* ``<compiler>``: ``angle`` (degree by default), ``eulerseq``, ``inertiafromgeom``,
  ``settotalmass``; ``coordinate="local"`` only;
* ``<option>``: ``timestep``, ``integrator`` (Euler, implicit, RK4), ``gravity``, ``density`` and
  ``viscosity`` (MuJoCo's inertia-box fluid forces);
* ``<default>`` classes (nested, inherited; ``class`` and ``childclass``);
* bodies with ``pos`` and any orientation (``quat``, ``axisangle``, ``euler``, ``xyaxes``,
  ``zaxis``), ``<inertial>`` or inertia from geoms (sphere, capsule, cylinder, ellipsoid, box;
  ``mass`` or ``density``), hinge and slide joints (armature, damping, stiffness, springref, ref,
  range/limited with solreflimit/solimplimit and margin), free and ball joints (``<freejoint>``
  too; armature and damping; quaternion coordinates as MuJoCo's), geoms (``fromto`` too) with their contact
  attributes, and ``<motor>`` actuators (gear, ctrlrange/ctrllimited, forcerange/forcelimited);
* ``<tendon>``: fixed tendons (a linear combination of hinge and slide coordinates) with their
  ``stiffness``, ``springlength`` and ``damping``.

MuJoCo's constraint-solver settings (``<option solver iterations tolerance ls_iterations cone
impratio>``) and the geoms' contact parameters (``margin``, ``solref``, ``solimp``, ``solmix``,
``priority``) are read: MuJoCo's contact model ([`constraint`][torchrl_diffenvs.articulated.constraint])
solves with them. Anything else that would change the dynamics
(limits or springs on ball joints, tendon limits, spatial tendons, equality constraints,
other actuators, wind and the ellipsoid fluid model, joint friction loss, ...) raises [`MJCFError`][torchrl_diffenvs.articulated.MJCFError] naming the
element, the attribute and the file. Purely visual things (materials, textures, lights, cameras,
sites, colours, sensors) are ignored.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .model import (ArticulatedModel, MJCFError, _z_to_vec, axis_angle_to_mat, geom_volume_inertia, mat_to_quat,
                    quat_to_mat)

__all__ = ["ArticulatedModel", "MJCFError", "gymnasium_asset", "load_mjcf"]


# ------------------------------------------------------------------ what the reader accepts
# Per element: attributes that change the dynamics and are read, and attributes that are ignored
# because they are visual or bookkeeping. Any other attribute raises.
_VISUAL = {"name", "rgba", "material", "group", "user", "class"}
_ORIENT = {"quat", "axisangle", "euler", "xyaxes", "zaxis"}
_READ = {
    "compiler": {"angle", "coordinate", "inertiafromgeom", "settotalmass", "eulerseq", "autolimits"},
    "option": {"timestep", "integrator", "gravity", "density", "viscosity", "solver", "iterations", "tolerance",
               "ls_iterations", "cone", "impratio"},
    "body": {"pos", "childclass"} | _ORIENT,
    "inertial": {"pos", "mass", "diaginertia", "fullinertia"} | _ORIENT,
    "joint": {
        "type", "axis", "pos", "range", "limited", "damping", "stiffness", "springref", "armature", "ref",
        "margin", "solreflimit", "solimplimit", "frictionloss",
    },
    "geom": {
        "type", "size", "pos", "fromto", "mass", "density", "friction", "contype", "conaffinity", "condim",
        "solref", "solimp", "margin", "solmix", "priority",
    } | _ORIENT,
    "motor": {"joint", "gear", "ctrlrange", "ctrllimited", "forcerange", "forcelimited"},
    "freejoint": set(),
    "fixed": {"stiffness", "damping", "springlength", "limited", "range"},
    "tendon_joint": {"joint", "coef"},
}
_IGNORED_ATTRS = {
    "compiler": {"meshdir", "texturedir", "assetdir"},
    # only read by magnetometer sensors
    "option": {"magnetic"},
    "body": {"name"},
    "geom": {"gap"},  # checked separately: only 0 is supported
}
# elements that never change the dynamics
_IGNORED_ELEMENTS = {"size", "visual", "asset", "custom", "light", "camera", "sensor", "statistic",
                     "keyframe", "extension"}
_DEFAULT_TAGS = {"joint", "geom", "motor", "general", "site", "camera", "light", "tendon", "mesh", "material",
                 "position", "velocity"}

_DEFAULT_SOLREF = (0.02, 1.0)
_DEFAULT_SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)



def gymnasium_asset(filename: str) -> Path:
    """The path of one of the model files that ship inside gymnasium (``envs/mujoco/assets``).

    Args:
        filename: the file's name there, e.g. ``"half_cheetah.xml"``.

    Raises:
        FileNotFoundError: the installed gymnasium ships no such file.
    """
    import gymnasium

    path = Path(gymnasium.__file__).parent / "envs" / "mujoco" / "assets" / filename
    if not path.is_file():
        raise FileNotFoundError(f"gymnasium {gymnasium.__version__} ships no MuJoCo model file {filename!r} ({path})")
    return path


# ------------------------------------------------------------------ small geometry helpers
def _floats(text: str, n: int | None = None, where: str = "") -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise MJCFError(f"{where}: expected numbers, got {text!r}") from None
    if n is not None and values.size != n:
        raise MJCFError(f"{where}: expected {n} numbers, got {values.size} ({text!r})")
    return values


class _Reader:
    def __init__(self, path: Path):
        self.path = str(path)
        self.root = ET.parse(path).getroot()
        if self.root.tag != "mujoco":
            raise MJCFError(f"{self.path}: the root element must be <mujoco>, got <{self.root.tag}>")
        self.angle_scale = math.pi / 180.0
        self.eulerseq = "xyz"
        self.inertia_from_geom = "auto"
        self.total_mass = None
        self.defaults: dict[str, dict[str, dict[str, str]]] = {}

    # ---------------------------------------------------------- checks
    def fail(self, element: ET.Element, message: str) -> MJCFError:
        name = element.get("name")
        what = f"<{element.tag}{' name=' + repr(name) if name else ''}>"
        return MJCFError(f"{self.path}: {what}: {message}")

    def check_attrs(self, element: ET.Element, tag: str | None = None) -> None:
        tag = tag or element.tag
        allowed = _READ.get(tag, set()) | _VISUAL | _IGNORED_ATTRS.get(tag, set())
        for attr in element.attrib:
            if attr not in allowed:
                raise self.fail(
                    element,
                    f"attribute {attr!r} is not supported (it would change the dynamics); supported: "
                    f"{sorted(_READ.get(tag, set()))}",
                )

    def attrs(self, element: ET.Element, tag: str, cls: str) -> dict[str, str]:
        """The element's attributes over its default class's (``class`` wins over ``childclass``)."""
        cls = element.get("class", cls)
        if cls not in self.defaults:
            raise self.fail(element, f"unknown default class {cls!r}; defined: {sorted(self.defaults)}")
        merged = dict(self.defaults[cls].get(tag, {}))
        merged.update(element.attrib)
        return merged

    # ---------------------------------------------------------- top level
    def read(self) -> ArticulatedModel:
        handlers = {"compiler": self.compiler, "option": self.option, "default": None,
                    "worldbody": None, "actuator": None, "tendon": None}
        self.timestep, self.integrator, self.gravity = 0.002, "euler", np.array([0.0, 0.0, -9.81])
        self.density = self.viscosity = 0.0
        self.solver_options = {}
        for child in self.root:
            if not isinstance(child.tag, str):  # comments
                continue
            if child.tag in _IGNORED_ELEMENTS:
                continue
            if child.tag not in handlers:
                raise self.fail(child, "element not supported (it would change the dynamics)")
            if handlers[child.tag] is not None:
                handlers[child.tag](child)
        self.defaults = {}
        for child in self.root.findall("default"):
            self.default(child, parent={})
        self.defaults.setdefault("main", {})
        self.bodies = dict(names=["world"], parent=[-1], pos=[np.zeros(3)], rot=[np.eye(3)], mass=[0.0],
                           com=[np.zeros(3)], inertia=[np.zeros((3, 3))])
        self.joints: list[dict] = []
        self.geoms: list[dict] = []
        self.sites: list[tuple] = []
        worlds = self.root.findall("worldbody")
        for world in worlds:
            self.body_children(world, body=0, cls="main")
        if self.total_mass is not None:
            scale = self.total_mass / sum(self.bodies["mass"][1:])
            self.bodies["mass"] = [m * scale for m in self.bodies["mass"]]
            self.bodies["inertia"] = [i * scale for i in self.bodies["inertia"]]
        self.tendons = []
        for tendons in self.root.findall("tendon"):
            for element in tendons:
                if isinstance(element.tag, str):
                    self.tendon(element)
        self.motors = []
        for actuators in self.root.findall("actuator"):
            for element in actuators:
                if isinstance(element.tag, str):
                    self.motor(element)
        return self.model()

    def compiler(self, element):
        self.check_attrs(element)
        angle = element.get("angle", "degree")
        if angle not in ("degree", "radian"):
            raise self.fail(element, f"angle must be 'degree' or 'radian', got {angle!r}")
        self.angle_scale = math.pi / 180.0 if angle == "degree" else 1.0
        if element.get("coordinate", "local") != "local":
            raise self.fail(element, "only coordinate='local' is supported (MuJoCo removed 'global')")
        self.eulerseq = element.get("eulerseq", "xyz")
        self.inertia_from_geom = element.get("inertiafromgeom", "auto")
        if element.get("settotalmass") is not None:
            total = float(element.get("settotalmass"))
            self.total_mass = total if total > 0 else None

    def option(self, element):
        self.check_attrs(element)
        for child in element:
            if isinstance(child.tag, str):
                raise self.fail(child, "<option> children (flags) are not supported")
        self.timestep = float(element.get("timestep", 0.002))
        integrator = element.get("integrator", "Euler")
        if integrator not in ("Euler", "implicit", "RK4"):
            raise self.fail(element, f"integrator {integrator!r} is not supported; supported: 'Euler', 'implicit', "
                                     "'RK4'")
        self.integrator = integrator.lower()
        self.gravity = _floats(element.get("gravity", "0 0 -9.81"), 3, f"{self.path}: <option gravity>")
        # MuJoCo's inertia-box fluid model (articulated.dynamics.fluid_force); the geom-level
        # ellipsoid model (fluidshape) and wind are not supported (unknown attributes raise)
        self.density = float(element.get("density", 0.0))
        self.viscosity = float(element.get("viscosity", 0.0))
        if self.density < 0 or self.viscosity < 0:
            raise self.fail(element, "density and viscosity must be >= 0")
        solver = element.get("solver", "Newton")
        if solver not in ("Newton", "CG", "PGS"):
            raise self.fail(element, f"solver {solver!r} is not supported; supported: 'Newton', 'CG', 'PGS'")
        cone = element.get("cone", "pyramidal")
        if cone not in ("pyramidal", "elliptic"):
            raise self.fail(element, f"cone {cone!r} is invalid; valid: 'pyramidal' (MuJoCo's default), 'elliptic'")
        options = dict(solver=solver.lower(), iterations=int(element.get("iterations", 100)),
                       tolerance=float(element.get("tolerance", 1e-8)),
                       ls_iterations=int(element.get("ls_iterations", 50)), cone=cone,
                       impratio=float(element.get("impratio", 1.0)))
        if options["iterations"] < 1 or options["ls_iterations"] < 1 or options["tolerance"] < 0 \
                or options["impratio"] <= 0:
            raise self.fail(element, "iterations and ls_iterations must be >= 1, tolerance >= 0 and impratio > 0")
        self.solver_options = options

    def default(self, element, parent):
        name = element.get("class", "main")
        own = {tag: dict(attrs) for tag, attrs in parent.items()}
        for child in element:
            if not isinstance(child.tag, str) or child.tag == "default":
                continue
            if child.tag not in _DEFAULT_TAGS:
                raise self.fail(child, "default for this element is not supported")
            tag = "motor" if child.tag in ("general", "position", "velocity") else child.tag
            own.setdefault(tag, {}).update(child.attrib)
        self.defaults[name] = own
        for child in element.findall("default"):
            self.default(child, own)

    # ---------------------------------------------------------- frames
    def orientation(self, element, attrs) -> np.ndarray:
        given = [k for k in _ORIENT if k in attrs]
        if len(given) > 1:
            raise self.fail(element, f"more than one orientation given: {given}")
        where = f"{self.path}: <{element.tag}>"
        if not given:
            return np.eye(3)
        kind = given[0]
        if kind == "quat":
            return quat_to_mat(_floats(attrs["quat"], 4, where))
        if kind == "axisangle":
            v = _floats(attrs["axisangle"], 4, where)
            return axis_angle_to_mat(v[:3], v[3] * self.angle_scale)
        if kind == "euler":
            angles = _floats(attrs["euler"], 3, where) * self.angle_scale
            rot = np.eye(3)
            for axis_name, angle in zip(self.eulerseq, angles):
                axis = np.eye(3)["xyz".index(axis_name.lower())]
                step = axis_angle_to_mat(axis, angle)
                # lower case: rotations about the moving (intrinsic) axes; upper case: fixed axes
                rot = rot @ step if axis_name.islower() else step @ rot
            return rot
        if kind == "xyaxes":
            v = _floats(attrs["xyaxes"], 6, where)
            x = v[:3] / np.linalg.norm(v[:3])
            y = v[3:] - x * (x @ v[3:])
            y = y / np.linalg.norm(y)
            return np.stack([x, y, np.cross(x, y)], axis=1)
        return _z_to_vec(_floats(attrs["zaxis"], 3, where))

    # ---------------------------------------------------------- bodies
    def body_children(self, element, body: int, cls: str):
        for child in element:
            if not isinstance(child.tag, str) or child.tag in _IGNORED_ELEMENTS:
                continue
            if child.tag == "body":
                self.body(child, parent=body, cls=cls)
            elif child.tag == "geom":
                self.geom(child, body, cls)
            elif child.tag in ("joint", "freejoint"):
                if body == 0:
                    raise self.fail(child, "a joint cannot belong to the world body")
                self.joint(child, body, cls)
            elif child.tag == "site":
                where = f"{self.path}: <site {child.get('name', '')}>"
                self.sites.append((child.get("name", f"site{len(self.sites)}"), body,
                                   _floats(child.get("pos", "0 0 0"), 3, where)))
            elif child.tag == "inertial":
                pass  # read by body()
            else:
                raise self.fail(child, "element not supported inside a body (it would change the dynamics)")

    def body(self, element, parent: int, cls: str):
        self.check_attrs(element)
        if element.get("mocap", "false") == "true":
            raise self.fail(element, "mocap bodies are not supported")
        cls = element.get("childclass", cls)
        index = len(self.bodies["names"])
        self.bodies["names"].append(element.get("name", f"body{index}"))
        self.bodies["parent"].append(parent)
        self.bodies["pos"].append(_floats(element.get("pos", "0 0 0"), 3, f"{self.path}: <body pos>"))
        self.bodies["rot"].append(self.orientation(element, element.attrib))
        for key in ("mass", "com", "inertia"):  # filled in below, once the children are read
            self.bodies[key].append(None)
        first_geom, first_joint = len(self.geoms), len(self.joints)
        self.body_children(element, index, cls)
        own = [joint for joint in self.joints[first_joint:] if joint["body"] == index]
        for joint in own[:-1]:
            if joint["type"] in ("ball", "free"):
                # MuJoCo takes a ball joint's dof axes from the body's final orientation ("no subsequent rotations")
                raise self.fail(joint["element"], f"a {joint['type']} joint must be the last joint of its body")
        inertial = element.find("inertial")
        use_geoms = self.inertia_from_geom == "true" or (self.inertia_from_geom == "auto" and inertial is None)
        if use_geoms:
            mass, com, inertia = self.inertia_of_geoms([g for g in self.geoms[first_geom:] if g["body"] == index])
        elif inertial is not None:
            mass, com, inertia = self.inertial(inertial)
        else:
            mass, com, inertia = 0.0, np.zeros(3), np.zeros((3, 3))
        self.bodies["mass"][index], self.bodies["com"][index], self.bodies["inertia"][index] = mass, com, inertia

    def inertial(self, element):
        self.check_attrs(element)
        where = f"{self.path}: <inertial>"
        mass = float(element.get("mass"))
        com = _floats(element.get("pos", "0 0 0"), 3, where)
        if "fullinertia" in element.attrib:
            v = _floats(element.get("fullinertia"), 6, where)  # ixx iyy izz ixy ixz iyz
            inertia = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
        else:
            inertia = np.diag(_floats(element.get("diaginertia"), 3, where))
        rot = self.orientation(element, element.attrib)
        return mass, com, rot @ inertia @ rot.T

    def inertia_of_geoms(self, geoms):
        """Body mass, com and inertia about the com from its geoms (MuJoCo's inertiafromgeom)."""
        parts = []
        for g in geoms:
            if g["type"] == "plane":
                continue
            vol, unit_inertia = geom_volume_inertia(g["type"], g["size"])
            density = g["mass"] / vol if g["mass"] is not None else g["density"]
            parts.append((density * vol, g["pos"], g["rot"] @ np.diag(density * unit_inertia) @ g["rot"].T))
        mass = sum(p[0] for p in parts)
        if mass <= 0:
            return 0.0, np.zeros(3), np.zeros((3, 3))
        com = sum(m * pos for m, pos, _ in parts) / mass
        inertia = np.zeros((3, 3))
        for m, pos, own in parts:
            d = pos - com
            inertia += own + m * (d @ d * np.eye(3) - np.outer(d, d))
        return mass, com, inertia

    def joint(self, element, body: int, cls: str):
        if element.tag == "freejoint":  # MuJoCo's shortcut for a free joint without springs or dampers
            self.check_attrs(element, "freejoint")
            a = {"name": element.get("name", f"joint{len(self.joints)}"), "type": "free"}
        else:
            a = self.attrs(element, "joint", cls)
            self.check_attrs(element)
            for attr in a:
                if attr not in _READ["joint"] | _VISUAL:
                    raise self.fail(element, f"attribute {attr!r} (from its default class) is not supported")
        kind = a.get("type", "hinge")
        if kind not in ("hinge", "slide", "ball", "free"):
            raise self.fail(element, f"joint type {kind!r} is not supported; supported: hinge, slide, ball, free")
        if float(a.get("frictionloss", 0.0)) != 0.0:
            raise self.fail(element, "frictionloss (dry joint friction) is not supported")
        where = f"{self.path}: <joint {a.get('name', '')}>"
        scale = self.angle_scale if kind == "hinge" else 1.0
        rng = _floats(a.get("range", "0 0"), 2, where) * scale
        limited = a.get("limited", "auto")
        limited = (rng[0] < rng[1]) if limited == "auto" else limited == "true"
        if kind in ("ball", "free"):
            # MuJoCo limits a ball joint's rotation angle (a cone) and its springs act on quaternions: neither is
            # modelled here, and a free joint can be neither
            if limited:
                raise self.fail(element, f"limits on a {kind} joint are not supported (set limited='false')")
            if float(a.get("stiffness", 0.0)) != 0.0:
                raise self.fail(element, f"stiffness on a {kind} joint is not supported")
            if kind == "free" and self.bodies["parent"][body] != 0:
                raise self.fail(element, "a free joint must belong to a child of the world body (as MuJoCo requires)")
        if limited and not rng[0] < rng[1]:
            raise self.fail(element, f"a limited joint needs range with lower < upper, got {a.get('range')!r}")
        axis = _floats(a.get("axis", "0 0 1"), 3, where)
        if kind == "free":  # its coordinates start at the body's file pose; its anchor is the body origin
            pos = np.zeros(3)
            ref = np.concatenate([self.bodies["pos"][body], mat_to_quat(self.bodies["rot"][body])])
            spring = ref
        elif kind == "ball":
            pos = _floats(a.get("pos", "0 0 0"), 3, where)
            ref = spring = np.array([1.0, 0.0, 0.0, 0.0])
        else:
            pos = _floats(a.get("pos", "0 0 0"), 3, where)
            ref = np.array([float(a.get("ref", 0.0)) * scale])
            spring = np.array([float(a.get("springref", 0.0)) * scale])
        self.joints.append(dict(
            name=a.get("name", f"joint{len(self.joints)}"), type=kind, body=body,
            axis=axis / np.linalg.norm(axis), pos=pos, ref=ref, springref=spring,
            stiffness=float(a.get("stiffness", 0.0)), damping=float(a.get("damping", 0.0)),
            armature=float(a.get("armature", 0.0)), limited=limited, range=rng,
            margin=float(a.get("margin", 0.0)),
            solref=_floats(a.get("solreflimit", "0.02 1"), 2, where),
            solimp=self.solimp(a.get("solimplimit"), where),
            element=element,
        ))

    @staticmethod
    def solimp(text, where):
        values = list(_DEFAULT_SOLIMP)
        if text is not None:
            given = _floats(text, None, where)
            values[: given.size] = given.tolist()
        return np.array(values)

    def geom(self, element, body: int, cls: str):
        a = self.attrs(element, "geom", cls)
        self.check_attrs(element)
        for attr in a:
            if attr not in _READ["geom"] | _VISUAL | _IGNORED_ATTRS["geom"]:
                raise self.fail(element, f"attribute {attr!r} (from its default class) is not supported")
        if float(a.get("gap", 0.0)) != 0.0:
            raise self.fail(element, "a non-zero contact gap is not supported")
        where = f"{self.path}: <geom {a.get('name', '')}>"
        kind = a.get("type", "sphere")
        if kind not in ("plane", "sphere", "capsule", "cylinder", "ellipsoid", "box"):
            raise self.fail(element, f"geom type {kind!r} is not supported; supported: plane, sphere, capsule, "
                                     "cylinder, ellipsoid, box")
        if a.get("condim", "3").strip() not in ("1", "3", "4", "6"):  # MuJoCo's compiler: "invalid condim in geom"
            raise self.fail(element, f"condim {a['condim']!r} is invalid; valid: 1, 3, 4, 6 (as MuJoCo's)")
        size = np.zeros(3)
        given = _floats(a.get("size", "0"), None, where)
        size[: given.size] = given
        if "fromto" in a:
            if kind not in ("capsule", "cylinder"):
                raise self.fail(element, f"fromto is only supported for capsules and cylinders, not {kind}")
            v = _floats(a["fromto"], 6, where)
            # MuJoCo points the geom's z axis from the second point to the first
            pos, rot = (v[:3] + v[3:]) / 2.0, _z_to_vec(v[:3] - v[3:])
            size[1] = np.linalg.norm(v[3:] - v[:3]) / 2.0
        else:
            pos, rot = _floats(a.get("pos", "0 0 0"), 3, where), self.orientation(element, a)
        friction = np.array([1.0, 0.005, 0.0001])
        fgiven = _floats(a.get("friction", "1"), None, where)
        friction[: fgiven.size] = fgiven
        self.geoms.append(dict(
            name=a.get("name"), type=kind, body=body, pos=pos, rot=rot, size=size,
            mass=float(a["mass"]) if "mass" in a else None, density=float(a.get("density", 1000.0)),
            friction=friction, contype=int(a.get("contype", 1)), conaffinity=int(a.get("conaffinity", 1)),
            condim=int(a.get("condim", 3)), margin=float(a.get("margin", 0.0)),
            solref=_floats(a.get("solref", "0.02 1"), 2, where), solimp=self.solimp(a.get("solimp"), where),
            solmix=float(a.get("solmix", 1.0)), priority=int(a.get("priority", 0)),
        ))

    def tendon(self, element):
        """A fixed tendon: length ``sum coef_j qpos_j`` over hinge and slide joints, with a spring
        ``-stiffness (length - springlength)`` and a damper ``-damping d(length)/dt`` on it."""
        if element.tag != "fixed":
            raise self.fail(element, "tendon type not supported; supported: <fixed>")
        a = self.attrs(element, "tendon", "main")
        self.check_attrs(element)
        for attr in a:
            if attr not in _READ["fixed"] | _VISUAL | {"width"}:
                raise self.fail(element, f"attribute {attr!r} (from its default class) is not supported")
        where = f"{self.path}: <fixed {a.get('name', '')}>"
        rng = _floats(a.get("range", "0 0"), 2, where)
        limited = a.get("limited", "auto")
        if (rng[0] < rng[1]) if limited == "auto" else limited == "true":
            raise self.fail(element, "tendon limits are not supported (a fixed tendon's spring and damper are)")
        names = [j["name"] for j in self.joints]
        coef = {}
        for child in element:
            if not isinstance(child.tag, str):
                continue
            if child.tag != "joint":
                raise self.fail(child, "a fixed tendon holds <joint joint=... coef=...> elements only")
            self.check_attrs(child, "tendon_joint")
            if child.get("joint") not in names:
                raise self.fail(child, f"unknown joint {child.get('joint')!r}; joints: {names}")
            j = names.index(child.get("joint"))
            if self.joints[j]["type"] not in ("hinge", "slide"):
                raise self.fail(child, "a fixed tendon's joints must be hinges or slides")
            coef[j] = coef.get(j, 0.0) + float(child.get("coef", "1"))
        if not coef:
            raise self.fail(element, "a fixed tendon needs at least one <joint>")
        spring = _floats(a.get("springlength", "-1"), None, where)
        if spring.size != 1:
            raise self.fail(element, "springlength with a deadband (two values) is not supported")
        self.tendons.append(dict(name=a.get("name", f"tendon{len(self.tendons)}"), coef=coef,
                                 stiffness=float(a.get("stiffness", 0.0)), damping=float(a.get("damping", 0.0)),
                                 springlength=float(spring[0])))

    def motor(self, element):
        if element.tag != "motor":
            raise self.fail(element, "actuator type not supported; supported: <motor>")
        a = self.attrs(element, "motor", "main")
        self.check_attrs(element)
        for attr in a:
            if attr not in _READ["motor"] | _VISUAL:
                raise self.fail(element, f"attribute {attr!r} (from its default class) is not supported")
        where = f"{self.path}: <motor {a.get('name', '')}>"
        if "joint" not in a:
            raise self.fail(element, "a motor needs a joint (other transmissions are not supported)")
        names = [j["name"] for j in self.joints]
        if a["joint"] not in names:
            raise self.fail(element, f"unknown joint {a['joint']!r}; joints: {names}")
        if self.joints[names.index(a["joint"])]["type"] not in ("hinge", "slide"):
            raise self.fail(element, "motors on ball and free joints are not supported (hinge and slide only)")

        def limits(flag, rng):
            values = _floats(a.get(rng, "0 0"), 2, where)
            on = a.get(flag, "auto")
            return ((values[0] < values[1]) if on == "auto" else on == "true"), values

        ctrl_limited, ctrl_range = limits("ctrllimited", "ctrlrange")
        force_limited, force_range = limits("forcelimited", "forcerange")
        gear = _floats(a.get("gear", "1"), None, where)
        if np.any(gear[1:] != 0):
            raise self.fail(element, "only the first gear component is supported (joint transmission)")
        self.motors.append(dict(
            name=a.get("name", f"actuator{len(self.motors)}"), joint=names.index(a["joint"]), gear=gear[0],
            ctrl_limited=ctrl_limited, ctrl_range=ctrl_range, force_limited=force_limited, force_range=force_range,
        ))

    # ---------------------------------------------------------- assembly
    def model(self) -> ArticulatedModel:
        b, j, g, m = self.bodies, self.joints, self.geoms, self.motors
        # MuJoCo numbers geoms body by body (a body's own geoms before its children's)
        g = sorted(g, key=lambda geom: geom["body"])
        for i, geom in enumerate(g):
            if geom["name"] is None:
                geom["name"] = f"geom{i}"

        def col(items, key, dtype=np.float64, shape=()):
            return np.array([it[key] for it in items], dtype=dtype).reshape(len(items), *shape)

        ndof = [{"hinge": 1, "slide": 1, "ball": 3, "free": 6}[x["type"]] for x in j]
        per_dof = lambda key: np.array([x[key] for x, n in zip(j, ndof) for _ in range(n)], dtype=np.float64)  # noqa: E731
        coordinates = lambda key: np.concatenate([x[key] for x in j]) if j else np.zeros(0)  # noqa: E731

        return ArticulatedModel(
            name=self.root.get("model", Path(self.path).stem), path=self.path, timestep=self.timestep,
            integrator=self.integrator, gravity=self.gravity, density=self.density, viscosity=self.viscosity,
            body_names=b["names"], body_parent=np.array(b["parent"], dtype=np.int64),
            body_pos=np.array(b["pos"]), body_rot=np.array(b["rot"]), body_mass=np.array(b["mass"]),
            body_com=np.array(b["com"]), body_inertia=np.array(b["inertia"]),
            joint_names=[x["name"] for x in j], joint_type=[x["type"] for x in j],
            joint_body=col(j, "body", np.int64), joint_axis=col(j, "axis", shape=(3,)),
            joint_pos=col(j, "pos", shape=(3,)),
            joint_qposadr=np.cumsum([0] + [len(x["ref"]) for x in j])[:-1].astype(np.int64),
            joint_dofadr=np.cumsum([0] + ndof)[:-1].astype(np.int64),
            qpos0=coordinates("ref"), qpos_spring=coordinates("springref"),
            stiffness=col(j, "stiffness"), damping=per_dof("damping"), armature=per_dof("armature"),
            dof_joint=np.repeat(np.arange(len(j)), ndof).astype(np.int64),
            limited=col(j, "limited", bool), joint_range=col(j, "range", shape=(2,)),
            limit_margin=col(j, "margin"), limit_solref=col(j, "solref", shape=(2,)),
            limit_solimp=col(j, "solimp", shape=(5,)),
            geom_names=[x["name"] for x in g], geom_type=[x["type"] for x in g], geom_body=col(g, "body", np.int64),
            geom_pos=col(g, "pos", shape=(3,)), geom_rot=col(g, "rot", shape=(3, 3)),
            geom_size=col(g, "size", shape=(3,)), geom_friction=col(g, "friction", shape=(3,)),
            geom_contype=col(g, "contype", np.int64), geom_conaffinity=col(g, "conaffinity", np.int64),
            geom_condim=col(g, "condim", np.int64), geom_margin=col(g, "margin"),
            geom_solref=col(g, "solref", shape=(2,)), geom_solimp=col(g, "solimp", shape=(5,)),
            geom_solmix=col(g, "solmix"), geom_priority=col(g, "priority", np.int64),
            actuator_names=[x["name"] for x in m], actuator_joint=col(m, "joint", np.int64),
            actuator_gear=col(m, "gear"), ctrl_limited=col(m, "ctrl_limited", bool),
            ctrl_range=col(m, "ctrl_range", shape=(2,)), force_limited=col(m, "force_limited", bool),
            force_range=col(m, "force_range", shape=(2,)),
            site_names=[x[0] for x in self.sites], site_body=np.array([x[1] for x in self.sites], dtype=np.int64),
            site_pos=np.array([x[2] for x in self.sites]).reshape(-1, 3),
            **self.tendon_arrays(j, ndof), **self.solver_options,
        )

    def tendon_arrays(self, joints, ndof) -> dict:
        """The fixed tendons as dense per-dof coefficients; a negative springlength is MuJoCo's
        "the length with the joints at their springref"."""
        dofadr = np.cumsum([0] + ndof)[:-1]
        coef = np.zeros((len(self.tendons), sum(ndof)))
        rest = np.zeros(len(self.tendons))
        for i, t in enumerate(self.tendons):
            for j, c in t["coef"].items():
                coef[i, dofadr[j]] = c
            # MuJoCo's default rest length: the tendon's length with every joint at its springref
            length0 = sum(c * float(joints[j]["springref"][0]) for j, c in t["coef"].items())
            rest[i] = length0 if t["springlength"] < 0 else t["springlength"]
        return dict(tendon_names=[t["name"] for t in self.tendons], tendon_coef=coef,
                    tendon_stiffness=np.array([t["stiffness"] for t in self.tendons]),
                    tendon_damping=np.array([t["damping"] for t in self.tendons]), tendon_springlength=rest)


def load_mjcf(path: str | Path) -> ArticulatedModel:
    """Reads an MJCF model file (see the module docstring for the supported subset).

    Args:
        path: the model file.

    Returns:
        The parsed [`ArticulatedModel`][torchrl_diffenvs.articulated.ArticulatedModel].

    Raises:
        FileNotFoundError: no file at ``path``.
        MJCFError: the file asks for something outside the supported subset, or is malformed.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no MJCF file at {path}")
    return _Reader(path).read()
