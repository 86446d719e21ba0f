"""Tests of the URDF+ reader (closedchain.urdf) and its error paths.

Every bad file is the real 4-bar model with one thing broken (string
replacement, written to tmp_path); every message must name the file, the
element and, where there is a finite set, the valid choices.
"""

from __future__ import annotations

import logging
import re
import socket
import warnings
from pathlib import Path

import numpy as np
import pytest

import closedchain as cc
from closedchain.urdf import LOOP_TYPES, parse_urdf

#: The 4-bar's loop element, as written in models/fourbar.urdf.
FOURBAR_LOOP = """  <loop name="C" type="revolute">
    <predecessor link="coupler"/>
    <successor link="rocker"/>
    <predecessor_origin xyz="0.4 0 0" rpy="0 0 0"/>
    <successor_origin xyz="0.3 0 0" rpy="0 0 0"/>
    <axis xyz="0 -1 0"/>
  </loop>"""


@pytest.fixture(scope="module")
def fourbar_text(mechanism_files) -> str:
    text = mechanism_files["fourbar"].read_text()
    assert text.count(FOURBAR_LOOP) == 1
    return text


@pytest.fixture
def write(tmp_path):
    """Return ``write(text, name="bad.urdf") -> Path``."""

    def _write(text: str, name: str = "bad.urdf") -> Path:
        path = tmp_path / name
        path.write_text(text)
        return path

    return _write


def replaced(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


def with_loop(text: str, loop: str) -> str:
    """Return the 4-bar text with its loop element replaced by ``loop``."""
    return replaced(text, FOURBAR_LOOP, loop)


def where(path: Path, element: str) -> str:
    """Regex for the location prefix of a message: file, line, element."""
    return re.escape(str(path)) + r": line \d+: " + re.escape(element)


# -- what a valid file yields ------------------------------------------------------------


def test_fourbar_extensions(mechanism_files):
    urdf = parse_urdf(mechanism_files["fourbar"])
    assert urdf.robot_name == "fourbar"
    assert urdf.links == ("ground", "crank", "coupler", "rocker")
    assert urdf.joints == {
        "crank_joint": "revolute",
        "coupler_joint": "revolute",
        "rocker_joint": "revolute",
    }
    assert urdf.actuated == ("crank_joint",)
    assert urdf.independent == ()
    (loop,) = urdf.loops
    assert (loop.name, loop.type, loop.predecessor, loop.successor) == (
        "C",
        "revolute",
        "coupler",
        "rocker",
    )
    assert np.array_equal(loop.predecessor_origin.translation, [0.4, 0.0, 0.0])
    assert np.array_equal(loop.successor_origin.translation, [0.3, 0.0, 0.0])
    assert np.array_equal(loop.predecessor_origin.rotation, np.eye(3))
    assert np.array_equal(loop.axis, [0.0, -1.0, 0.0])


def test_axis_is_normalized_and_origins_default_to_identity(fourbar_text, write):
    loop = """  <loop name="C" type="revolute">
    <predecessor link="coupler"/>
    <successor link="rocker"/>
    <axis xyz="0 -2.5 0"/>
  </loop>"""
    (spec,) = parse_urdf(write(with_loop(fourbar_text, loop))).loops
    assert np.array_equal(spec.axis, [0.0, -1.0, 0.0])
    assert np.array_equal(spec.predecessor_origin.homogeneous, np.eye(4))
    assert np.array_equal(spec.successor_origin.homogeneous, np.eye(4))


def test_origin_rpy_is_the_urdf_convention(fourbar_text, write):
    """URDF rpy: R = Rz(yaw) Ry(pitch) Rx(roll), fixed axes."""
    r, p, y = 0.3, -0.4, 1.1
    loop = FOURBAR_LOOP.replace(
        '<predecessor_origin xyz="0.4 0 0" rpy="0 0 0"/>',
        f'<predecessor_origin xyz="0.4 0 0" rpy="{r} {p} {y}"/>',
    )
    (spec,) = parse_urdf(write(with_loop(fourbar_text, loop))).loops

    def Rx(t):
        return np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])

    def Ry(t):
        return np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])

    def Rz(t):
        return np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])

    expected = Rz(y) @ Ry(p) @ Rx(r)
    assert np.linalg.norm(spec.predecessor_origin.rotation - expected) <= 1e-15


def test_spherical_loop_needs_no_axis(fourbar_text, write):
    loop = FOURBAR_LOOP.replace('type="revolute"', 'type="spherical"').replace(
        '    <axis xyz="0 -1 0"/>\n', ""
    )
    (spec,) = parse_urdf(write(with_loop(fourbar_text, loop))).loops
    assert spec.type == "spherical"


# -- XML level ----------------------------------------------------------------------------


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.urdf"
    with pytest.raises(cc.ModelFileError, match=re.escape(str(path)) + ": cannot read URDF file"):
        cc.load(path)


def test_malformed_xml(fourbar_text, write):
    path = write(fourbar_text[: len(fourbar_text) // 2])
    with pytest.raises(cc.ModelFileError, match=re.escape(str(path)) + ": malformed XML"):
        cc.load(path)


def test_root_must_be_robot(fourbar_text, write):
    path = write(fourbar_text.replace("<robot ", "<sdf ").replace("</robot>", "</sdf>"))
    with pytest.raises(
        cc.ModelFileError, match=re.escape(str(path)) + r": root element is <sdf>, expected <robot>"
    ):
        cc.load(path)


BILLION_LAUGHS = """<!DOCTYPE robot [
  <!ENTITY lol "lol">
  <!ENTITY lol1 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
  <!ENTITY lol2 "&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;">
  <!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">
  <!ENTITY lol4 "&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;">
  <!ENTITY lol5 "&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;">
  <!ENTITY lol6 "&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;&lol5;">
  <!ENTITY lol7 "&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;&lol6;">
  <!ENTITY lol8 "&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;&lol7;">
  <!ENTITY lol9 "&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;&lol8;">
]>
"""


def _with_doctype(text: str, doctype: str, entity: str | None, where: str = "attribute") -> str:
    """Insert a DOCTYPE before the header comment; reference ``entity`` in an attribute or text."""
    head, body = text.split("\n", 1)  # keep the XML declaration first
    assert head.startswith("<?xml")
    if entity is not None and where == "attribute":
        body = replaced(body, '<robot name="fourbar">', f'<robot name="&{entity};">')
    elif entity is not None:
        body = replaced(
            body, "<type>transmission_interface", f"<type>&{entity};transmission_interface"
        )
    return f"{head}\n{doctype}{body}"


@pytest.mark.parametrize("where_ref", ["attribute", "text"])
def test_billion_laughs_is_refused(fourbar_text, write, where_ref):
    path = write(_with_doctype(fourbar_text, BILLION_LAUGHS, "lol9", where_ref))
    with pytest.raises(
        cc.ModelFileError, match=re.escape(str(path)) + r": a DOCTYPE/DTD is not allowed"
    ):
        cc.load(path)


def test_doctype_after_the_header_comment_is_refused(fourbar_text, write):
    text = replaced(
        fourbar_text, '<robot name="fourbar">', BILLION_LAUGHS + '<robot name="&lol9;">'
    )
    path = write(text)
    with pytest.raises(
        cc.ModelFileError, match=re.escape(str(path)) + r": a DOCTYPE/DTD is not allowed"
    ):
        cc.load(path)


@pytest.fixture
def listener():
    """A local TCP socket: a parser that fetches an external entity would connect to it."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen(4)
    sock.setblocking(False)
    yield sock
    sock.close()


def _assert_no_connection(sock):
    with pytest.raises(BlockingIOError):
        conn, _ = sock.accept()
        conn.close()


@pytest.mark.parametrize("kind", ["file", "http", "parameter", "external_dtd"])
def test_external_entities_are_refused_never_expanded_or_fetched(
    fourbar_text, write, tmp_path, listener, kind
):
    secret = tmp_path / "secret.txt"
    marker = "TOP-SECRET-MARKER-1234"
    secret.write_text(marker)
    url = f"http://127.0.0.1:{listener.getsockname()[1]}/x"
    doctypes = {
        "file": (f'<!DOCTYPE robot [<!ENTITY xxe SYSTEM "file://{secret}">]>\n', "xxe"),
        "http": (f'<!DOCTYPE robot [<!ENTITY xxe SYSTEM "{url}">]>\n', "xxe"),
        "parameter": (f'<!DOCTYPE robot [<!ENTITY % p SYSTEM "{url}"> %p;]>\n', None),
        "external_dtd": (f'<!DOCTYPE robot SYSTEM "{url}.dtd">\n', None),
    }
    doctype, entity = doctypes[kind]
    path = write(_with_doctype(fourbar_text, doctype, entity))
    with pytest.raises(
        cc.ModelFileError, match=re.escape(str(path)) + r": a DOCTYPE/DTD is not allowed"
    ) as info:
        cc.load(path)
    assert marker not in str(info.value)
    _assert_no_connection(listener)


def test_robot_without_links(write):
    path = write('<?xml version="1.0"?>\n<robot name="empty"></robot>\n')
    with pytest.raises(cc.ModelFileError, match=re.escape(str(path)) + r": <robot> has no <link>"):
        cc.load(path)


# -- <loop> ---------------------------------------------------------------------------------


def test_unknown_loop_type_lists_the_valid_types(fourbar_text, write):
    path = write(with_loop(fourbar_text, FOURBAR_LOOP.replace('"revolute"', '"ball"')))
    assert LOOP_TYPES == ("revolute", "prismatic", "spherical", "fixed", "coupling")
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<loop name='C'>")
        + r": unknown loop type 'ball'; valid choices: revolute, prismatic, spherical, fixed, "
        "coupling",
    ):
        cc.load(path)


def test_unknown_link_lists_the_links(fourbar_text, write):
    path = write(with_loop(fourbar_text, FOURBAR_LOOP.replace('"rocker"', '"roker"')))
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<loop name='C'>") + r": <successor link='roker'> names an unknown link; "
        r"links: coupler, crank, ground, rocker",
    ):
        cc.load(path)


@pytest.mark.parametrize("axis", ["0 0 0", "0 -0 0.0"])
def test_zero_axis(fourbar_text, write, axis):
    path = write(with_loop(fourbar_text, FOURBAR_LOOP.replace('"0 -1 0"', f'"{axis}"')))
    with pytest.raises(
        cc.ModelFileError, match=where(path, "<loop name='C'>") + rf": <axis xyz='{axis}'> is zero"
    ):
        cc.load(path)


@pytest.mark.parametrize(
    "xyz", ["0.4 0", "0.4 0 0 0", "a b c", "0.4 nan 0", "0.4 inf 0", "0.4,0,0", ""]
)
def test_bad_xyz_attribute(fourbar_text, write, xyz):
    loop = FOURBAR_LOOP.replace(
        'predecessor_origin xyz="0.4 0 0"', f'predecessor_origin xyz="{xyz}"'
    )
    path = write(with_loop(fourbar_text, loop))
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<predecessor_origin>")
        + re.escape(f": attribute xyz={xyz!r} must be three finite numbers"),
    ):
        cc.load(path)


def test_bad_rpy_attribute(fourbar_text, write):
    loop = FOURBAR_LOOP.replace(
        'successor_origin xyz="0.3 0 0" rpy="0 0 0"', 'successor_origin xyz="0.3 0 0" rpy="0 0"'
    )
    path = write(with_loop(fourbar_text, loop))
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<successor_origin>") + re.escape(": attribute rpy='0 0' must be"),
    ):
        cc.load(path)


def test_duplicate_loop_names(fourbar_text, write):
    path = write(with_loop(fourbar_text, FOURBAR_LOOP + "\n" + FOURBAR_LOOP))
    with pytest.raises(
        cc.ModelFileError, match=re.escape(str(path)) + r": loop name 'C' is used more than once"
    ):
        cc.load(path)


def test_loop_needs_a_name(fourbar_text, write):
    path = write(with_loop(fourbar_text, FOURBAR_LOOP.replace(' name="C"', "")))
    with pytest.raises(cc.ModelFileError, match=where(path, "<loop>") + r": <loop> needs a name"):
        cc.load(path)


@pytest.mark.parametrize("tag", ["predecessor", "successor"])
def test_loop_needs_both_links(fourbar_text, write, tag):
    loop = "\n".join(ln for ln in FOURBAR_LOOP.split("\n") if f"<{tag} " not in ln)
    path = write(with_loop(fourbar_text, loop))
    with pytest.raises(
        cc.ModelFileError, match=where(path, "<loop name='C'>") + f": missing <{tag}>"
    ):
        cc.load(path)


@pytest.mark.parametrize("loop_type", ["revolute", "prismatic"])
def test_revolute_and_prismatic_loops_need_an_axis(fourbar_text, write, loop_type):
    loop = FOURBAR_LOOP.replace('"revolute"', f'"{loop_type}"').replace(
        '    <axis xyz="0 -1 0"/>\n', ""
    )
    path = write(with_loop(fourbar_text, loop))
    with pytest.raises(
        cc.ModelFileError, match=where(path, "<loop name='C'>") + ": missing <axis>"
    ):
        cc.load(path)


def test_loop_with_two_axes(fourbar_text, write):
    loop = FOURBAR_LOOP.replace('<axis xyz="0 -1 0"/>', '<axis xyz="0 -1 0"/><axis xyz="1 0 0"/>')
    path = write(with_loop(fourbar_text, loop))
    with pytest.raises(
        cc.ModelFileError, match=where(path, "<loop name='C'>") + ": more than one <axis>"
    ):
        cc.load(path)


def test_loop_between_a_link_and_itself(fourbar_text, write):
    path = write(with_loop(fourbar_text, FOURBAR_LOOP.replace('"rocker"', '"coupler"')))
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<loop name='C'>") + ": predecessor and successor are the same link",
    ):
        cc.load(path)


#: A link welded to the crank by a fixed joint (so it moves with crank_joint).
CRANK_TIP = """  <link name="crank_tip"/>
  <joint name="crank_tip_joint" type="fixed">
    <parent link="crank"/>
    <child link="crank_tip"/>
    <origin xyz="0.2 0 0" rpy="0 0 0"/>
  </joint>
"""


def test_loop_between_links_moved_by_the_same_joint(fourbar_text, write):
    loop = FOURBAR_LOOP.replace('"coupler"', '"crank"').replace('"rocker"', '"crank_tip"')
    text = with_loop(fourbar_text, CRANK_TIP + loop)
    path = write(text)
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(str(path))
        + r": line \d+: <loop name='C'>: predecessor 'crank' and successor 'crank_tip' "
        r"move with the same joint, so the loop closes nothing",
    ):
        cc.load(path)


def test_loop_whose_frames_cannot_be_brought_together(fourbar_text, write):
    """A 2 m coupler cannot close a loop whose other links span at most 1 m."""
    loop = FOURBAR_LOOP.replace(
        'predecessor_origin xyz="0.4 0 0"', 'predecessor_origin xyz="2.0 0 0"'
    )
    path = write(with_loop(fourbar_text, loop))
    with pytest.raises(
        cc.LoopClosureError,
        match=re.escape(str(path)) + r": the loop frames cannot be brought together .*"
        r"\(per loop: C: \d",
    ) as info:
        cc.load(path)
    # The smallest reachable gap: the coupler end stays >= 1.8 m from A, the
    # rocker end <= 0.8 m from A, so some |phi| component is >= 1.0 / sqrt(2).
    best = float(re.search(r"smallest max \|phi\| reached ([0-9.e+-]+)", str(info.value))[1])
    assert best >= 1.0 / np.sqrt(2) - 1e-3


def test_links_that_make_no_tree(fourbar_text, write):
    path = write(
        replaced(
            fourbar_text, '<link name="crank">', '<link name="orphan"/>\n  <link name="crank">'
        )
    )
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(
            f"{path}: the links and joints make no tree: 2 root links (ground, orphan)"
        ),
    ):
        cc.load(path)


# -- <transmission> and independent ----------------------------------------------------------


def test_transmission_naming_a_missing_joint(fourbar_text, write):
    path = write(
        replaced(
            fourbar_text,
            '<joint name="crank_joint">\n      <hardware',
            '<joint name="crank_jont">\n      <hardware',
        )
    )
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<transmission name='crank_transmission'>")
        + r": names joint 'crank_jont', which is not a <joint> of this file; "
        r"joints: coupler_joint, crank_joint, rocker_joint",
    ):
        cc.load(path)


def test_transmission_without_joint(fourbar_text, write):
    text = replaced(
        fourbar_text,
        '<transmission name="crank_transmission">',
        '<transmission name="empty"><type>x</type></transmission>\n'
        '  <transmission name="crank_transmission">',
    )
    path = write(text)
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<transmission name='empty'>") + ": has no <joint> child",
    ):
        cc.load(path)


def test_transmission_on_a_fixed_joint(fourbar_text, write):
    text = replaced(fourbar_text, FOURBAR_LOOP, CRANK_TIP + FOURBAR_LOOP)
    text = replaced(
        text,
        '<joint name="crank_joint">\n      <hardware',
        '<joint name="crank_tip_joint">\n      <hardware',
    )
    path = write(text)
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<transmission name='crank_transmission'>")
        + ": joint 'crank_tip_joint' is fixed and cannot be actuated",
    ):
        cc.load(path)


def test_independent_must_be_true_or_false(fourbar_text, write):
    text = replaced(
        fourbar_text,
        '<joint name="rocker_joint" type="revolute">',
        '<joint name="rocker_joint" type="revolute" independent="yes">',
    )
    path = write(text)
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<joint name='rocker_joint'>")
        + ': independent=\'yes\' must be "true" or "false"',
    ):
        cc.load(path)


def test_fixed_joint_cannot_be_independent(fourbar_text, write):
    tip = CRANK_TIP.replace('type="fixed"', 'type="fixed" independent="true"')
    path = write(replaced(fourbar_text, FOURBAR_LOOP, tip + FOURBAR_LOOP))
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<joint name='crank_tip_joint'>")
        + ": a fixed joint cannot be independent",
    ):
        cc.load(path)


def test_independent_false_is_the_default(fourbar_text, write):
    text = replaced(
        fourbar_text,
        '<joint name="rocker_joint" type="revolute">',
        '<joint name="rocker_joint" type="revolute" independent="false">',
    )
    mech = cc.load(write(text))
    assert mech.description.independent == ()
    assert mech.independent_source == "actuated"


# -- the tree: inertials, joint origins, axes and limits (urdfdom only warns) ------------

CRANK_MASS = '<mass value="1.0"/>\n      <!-- m a^2 / 12 = 1 * 0.2^2 / 12 -->'
CRANK_INERTIA = (
    '<inertia ixx="0" ixy="0" ixz="0" iyy="0.0033333333333333335" iyz="0" '
    'izz="0.0033333333333333335"/>'
)
CRANK_JOINT_AXIS = """  <joint name="crank_joint" type="revolute">
    <parent link="ground"/>
    <child link="crank"/>
    <origin xyz="0 0 0" rpy="0 0 0"/>
    <axis xyz="0 -1 0"/>
    <limit lower="-6.283185307179586" upper="6.283185307179586" effort="50" velocity="50"/>"""


def crank_link_where(path: Path) -> str:
    return re.escape(str(path)) + r": line \d+: " + re.escape("<link name='crank'> <inertial>")


@pytest.mark.parametrize("mass", ["nan", "abc", "-1", "inf", ""])
def test_inertial_mass_must_be_finite_and_non_negative(fourbar_text, write, mass):
    path = write(
        replaced(
            fourbar_text,
            '<mass value="1.0"/>\n      <!-- m a^2 / 12',
            f'<mass value="{mass}"/>\n      <!-- m a^2 / 12',
        )
    )
    with pytest.raises(
        cc.ModelFileError,
        match=crank_link_where(path) + r" <mass value=.*must be a finite number >= 0",
    ):
        cc.load(path)


@pytest.mark.parametrize(
    ("inertia", "message"),
    [
        ('ixx="-1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"', "not positive semi-definite"),
        ('ixx="1" ixy="2" ixz="0" iyy="1" iyz="0" izz="1"', "not positive semi-definite"),
        ('ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="1"', "triangle inequality"),
        (
            'ixx="nan" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"',
            r"<inertia ixx='nan'>: must be a finite",
        ),
    ],
)
def test_inertia_must_be_a_rigid_body_inertia(fourbar_text, write, inertia, message):
    path = write(replaced(fourbar_text, CRANK_INERTIA, f"<inertia {inertia}/>"))
    with pytest.raises(cc.ModelFileError, match=crank_link_where(path) + ".*" + message):
        cc.load(path)


def test_inertial_without_mass(fourbar_text, write):
    path = write(
        replaced(fourbar_text, '<mass value="1.0"/>\n      <!-- m a^2 / 12', "<!-- m a^2 / 12")
    )
    with pytest.raises(cc.ModelFileError, match=crank_link_where(path) + ": missing <mass"):
        cc.load(path)


def joint_where(path: Path, name: str) -> str:
    return re.escape(str(path)) + r": line \d+: " + re.escape(f"<joint name={name!r}>")


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            '<origin xyz="0 0 0" rpy="0 0 0"/>',
            '<origin xyz="0 nan 0" rpy="0 0 0"/>',
            r" <origin>: attribute xyz='0 nan 0' must be three finite",
        ),
        (
            '<origin xyz="0 0 0" rpy="0 0 0"/>',
            '<origin xyz="0 0 0" rpy="inf 0 0"/>',
            r" <origin>: attribute rpy='inf 0 0' must be three finite",
        ),
        ('<axis xyz="0 -1 0"/>', '<axis xyz="0 0 0"/>', r": <axis xyz='0 0 0'> is zero; valid: "),
        ('<axis xyz="0 -1 0"/>', '<axis xyz="0 nan 0"/>', r": <axis xyz='0 nan 0'> is not finite"),
        ('<axis xyz="0 -1 0"/>', '<axis xyz="0 1e309 0"/>', r": <axis xyz='0 1e309 0'> is not fin"),
        ('<axis xyz="0 -1 0"/>', '<axis xyz="0 1"/>', r": <axis xyz='0 1'> must be three numbers"),
        (
            'lower="-6.283185307179586"',
            'lower="nan"',
            r" <limit lower='nan'>: must be a finite number$",
        ),
        (
            'upper="6.283185307179586"',
            'upper="abc"',
            r" <limit upper='abc'>: must be a finite number$",
        ),
        ('effort="50"', 'effort="-5"', r" <limit effort='-5'>: must be a finite number >= 0"),
        ('lower="-6.283185307179586"', 'lower="7"', r" <limit>: lower=7 exceeds upper=6.28319"),
    ],
)
def test_joint_origin_axis_and_limits_are_checked(fourbar_text, write, old, new, message):
    path = write(replaced(fourbar_text, CRANK_JOINT_AXIS, CRANK_JOINT_AXIS.replace(old, new)))
    with pytest.raises(cc.ModelFileError, match=joint_where(path, "crank_joint") + message):
        cc.load(path)


def test_zero_axis_of_a_fixed_joint_is_ignored(fourbar_text, write):
    # URDF ignores the axis of fixed joints; real robots (Talos) write 0 0 0 there.
    text = fourbar_text.replace(
        "</robot>",
        '<link name="tag"/><joint name="tag_joint" type="fixed"><parent link="crank"/>'
        '<child link="tag"/><axis xyz="0 0 0"/></joint></robot>',
    )
    mech = cc.load(write(text))
    assert mech.model.existFrame("tag")


# -- the <scene> element --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("scene", "message"),
    [
        (
            '<scene><initial joint="nope" value="1"/></scene>',
            r"<initial>: joint='nope' is not a revolute or prismatic joint of this file; "
            r"valid: coupler_joint, crank_joint, rocker_joint",
        ),
        (
            '<scene><initial joint="crank_joint" value="nan"/></scene>',
            r"<initial> <initial value='nan'>: must be a finite number",
        ),
        ('<scene><initial joint="crank_joint"/></scene>', r"<initial>: missing value="),
        (
            '<scene><initial joint="crank_joint" value="0.2" velocity="1e200"/></scene>',
            r"<initial velocity='1e200'>: must be within \+-1e\+06",
        ),
        (
            '<scene><track kp="1"><sinusoid joint="crank_joint"/></track></scene>',
            r"<track>: missing kd= \(a gain >= 0\)",
        ),
        (
            '<scene><track kp="-1" kd="1"><sinusoid joint="crank_joint"/></track></scene>',
            r"<track kp='-1'>: must be a finite number >= 0",
        ),
        (
            '<scene><track kp="1" kd="1"></track></scene>',
            r"<track>: has no <sinusoid joint=...> child",
        ),
        (
            '<scene><track kp="1" kd="1"><sinusoid joint="crank_joint" frequency="-2"/>'
            "</track></scene>",
            r"<sinusoid frequency='-2'>: must be a finite number >= 0",
        ),
        ("<scene/><scene/>", r"<scene>: more than one <scene> \(at most one\)"),
    ],
)
def test_bad_scene(fourbar_text, write, scene, message):
    start = fourbar_text.index("  <scene>")
    end = fourbar_text.index("</scene>") + len("</scene>")
    path = write(fourbar_text[:start] + scene + fourbar_text[end:])
    with pytest.raises(cc.ModelFileError, match=re.escape(str(path)) + r": line \d+: .*" + message):
        cc.load(path)


# -- numbers that overflow: axes scaled before their norm, origins within a bound ------------


def line_of(text: str, marker: str) -> int:
    """Return the 1-based line of the first occurrence of ``marker`` in ``text``."""
    return text[: text.index(marker)].count("\n") + 1


@pytest.mark.parametrize("y", ["-1e200", "-1e308", "-1.7976931348623157e308", "-1e-12", "-5e-324"])
def test_joint_axis_is_normalized_without_overflow(fourbar, fourbar_text, write, y):
    """Any finite non-zero axis is a direction: Pinocchio gets the same unit axis as written."""
    path = write(
        replaced(fourbar_text, CRANK_JOINT_AXIS, CRANK_JOINT_AXIS.replace('"0 -1 0"', f'"0 {y} 0"'))
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning (overflow in the norm)
        mech = cc.load(path)
    crank = mech.model.joints[mech.model.getJointId("crank_joint")]
    assert np.array_equal(crank.extract().axis, [0.0, -1.0, 0.0])
    assert mech.mobility == 1
    (crank,) = (j for j in mech.description.tree.joints() if j.name == "crank_joint")
    assert np.array_equal(crank.axis, [0.0, -1.0, 0.0])
    assert mech.digest() == fourbar.digest()


@pytest.mark.parametrize("y", ["-1e308", "-5e-324"])
def test_loop_axis_is_normalized_without_overflow(fourbar_text, write, y):
    path = write(with_loop(fourbar_text, FOURBAR_LOOP.replace('"0 -1 0"', f'"0 {y} 0"')))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (spec,) = parse_urdf(path).loops
    assert np.array_equal(spec.axis, [0.0, -1.0, 0.0])


@pytest.mark.parametrize(
    ("axis", "what"),
    [("0 -1e309 0", "is not finite"), ("nan 0 0", "is not finite"), ("0 0 -0", "is zero")],
)
def test_loop_axis_that_is_not_finite_or_zero_says_which(fourbar_text, write, axis, what):
    path = write(with_loop(fourbar_text, FOURBAR_LOOP.replace('"0 -1 0"', f'"{axis}"')))
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(f"{path}: line {line_of(fourbar_text, '<loop ')}: <loop name='C'>: ")
        + re.escape(f"<axis xyz={axis!r}> {what}"),
    ):
        parse_urdf(path)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (  # joint origin
            '<origin xyz="0.5 0 0" rpy="0 0 0"/>',
            '<origin xyz="1e308 0 0" rpy="0 0 0"/>',
            "<joint name='rocker_joint'> <origin>: attribute xyz='1e308 0 0' is beyond "
            "ORIGIN_XYZ_MAX = 1e+06 m",
        ),
        (
            '<origin xyz="0.5 0 0" rpy="0 0 0"/>',
            '<origin xyz="0.5 0 0" rpy="0 1e300 0"/>',
            "<joint name='rocker_joint'> <origin>: attribute rpy='0 1e300 0' is beyond "
            "ORIGIN_RPY_MAX = 1000 rad",
        ),
        (  # loop origin
            '<successor_origin xyz="0.3 0 0" rpy="0 0 0"/>',
            '<successor_origin xyz="0.3 -2e6 0" rpy="0 0 0"/>',
            "<successor_origin>: attribute xyz='0.3 -2e6 0' is beyond ORIGIN_XYZ_MAX",
        ),
        (  # inertial origin
            '<origin xyz="0.15 0 0" rpy="0 0 0"/>\n      <mass',
            '<origin xyz="1e200 0 0" rpy="0 0 0"/>\n      <mass',
            "<link name='rocker'> <inertial> <origin>: attribute xyz='1e200 0 0' is beyond",
        ),
        (  # visual origin
            '<origin xyz="0.15 0 0" rpy="0 0 0"/>\n      <geometry>',
            '<origin xyz="0.15 0 0" rpy="-1e4 0 0"/>\n      <geometry>',
            "<link name='rocker'> <visual> <origin>: attribute rpy='-1e4 0 0' is beyond",
        ),
    ],
)
def test_origins_beyond_their_bound_are_refused_without_warnings(
    fourbar_text, write, old, new, message
):
    path = write(replaced(fourbar_text, old, new))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(
            cc.ModelFileError, match=re.escape(str(path)) + r": line \d+: .*" + re.escape(message)
        ):
            cc.load(path)


# -- unknown and misplaced elements ---------------------------------------------------------


def test_loop_inside_a_link_is_refused(fourbar_text, write):
    """Ignored, it would leave the mechanism open (the Agile Eye would report mobility 5)."""
    text = replaced(
        with_loop(fourbar_text, ""), "</link>\n\n  <joint", FOURBAR_LOOP + "\n  </link>\n\n  <joint"
    )
    path = write(text)
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(
            f"{path}: line {line_of(text, '<loop ')}: <loop name='C'>: inside <link name='rocker'>:"
            " a <loop> is read only as a child of <robot>"
        ),
    ):
        cc.load(path)


def test_loop_inside_the_agile_eye_link_is_refused(mechanism_files, write):
    text = mechanism_files["agile_eye"].read_text()
    start = text.index('  <loop name="leg1_platform"')
    end = text.index("</loop>", start) + len("</loop>")
    loop = text[start:end]
    text = text[:start] + text[end:]
    text = replaced(text, '<link name="euler_link_z"/>', f'<link name="euler_link_z">{loop}</link>')
    path = write(text)
    with pytest.raises(
        cc.ModelFileError,
        match=rf"line {line_of(text, loop)}: <loop name='leg1_platform'>: "
        r"inside <link name='euler_link_z'>",
    ):
        cc.load(path)


def test_scene_inside_a_joint_is_refused(fourbar_text, write):
    start, end = fourbar_text.index("  <scene>"), fourbar_text.index("</scene>") + len("</scene>")
    scene = fourbar_text[start:end]
    text = replaced(
        fourbar_text[:start] + fourbar_text[end:],
        '<child link="rocker"/>',
        '<child link="rocker"/>' + scene,
    )
    path = write(text)
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(
            f"line {line_of(text, '<scene>')}: <scene>: inside <joint name='rocker_joint'>"
        ),
    ):
        cc.load(path)


def test_loop_inside_gazebo_is_not_urdf_and_is_left_alone(fourbar_text, write):
    # SDF (in <gazebo>) has its own <loop> (audio sources); URDF tools skip <gazebo>.
    text = replaced(
        fourbar_text,
        "</robot>",
        "<gazebo><audio_source><loop>true</loop></audio_source></gazebo></robot>",
    )
    assert cc.load(write(text)).mobility == 1


@pytest.mark.parametrize(
    ("tag", "typo"),
    [("loop", "Loop"), ("transmission", "transmision"), ("scene", "scnee"), ("joint", "joints")],
)
def test_misspelled_top_level_element_is_refused(fourbar_text, write, tag, typo):
    """Ignored, it would change the mechanism (or its actuation, or its scene) silently."""
    start = fourbar_text.index(f"<{tag}>" if tag == "scene" else f"<{tag} ")
    end = fourbar_text.index(f"</{tag}>", start)
    text = (
        fourbar_text[:start]
        + f"<{typo}"
        + fourbar_text[start + len(tag) + 1 : end]
        + f"</{typo}>"
        + fourbar_text[end + len(tag) + 3 :]
    )
    path = write(text)
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(f"{path}: line {line_of(text, f'<{typo}')}: <{typo}")
        + r"( name='\w+')?>"
        + re.escape(f": unknown element (it would be ignored); did you mean <{tag}>?"),
    ):
        cc.load(path)


def test_unknown_top_level_element_is_a_warning_naming_file_and_line(fourbar_text, write, caplog):
    text = replaced(fourbar_text, "</robot>", '<sensor name="cam"/>\n  <gazebo/>\n</robot>')
    path = write(text)
    with caplog.at_level(logging.WARNING, logger="closedchain.urdf"):
        mech = cc.load(path)
    assert mech.mobility == 1
    assert [r.getMessage() for r in caplog.records if r.name == "closedchain.urdf"] == [
        f"{path}: line {line_of(text, '<sensor')}: <sensor name='cam'>: not a URDF or URDF+ "
        "element; ignored"
    ]


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            '<axis xyz="0 -1 0"/>\n  </loop>',
            '<axsi xyz="0 -1 0"/>\n  </loop>',
            "<axsi>: unknown element in <loop> (it would be ignored); did you mean <axis>?",
        ),
        (
            '<predecessor_origin xyz="0.4 0 0" rpy="0 0 0"/>',
            '<origin xyz="0.4 0 0" rpy="0 0 0"/>',
            "<origin>: unknown element in <loop>; valid: <predecessor>, <successor>, "
            "<predecessor_origin>, <successor_origin>, <axis>",
        ),
        (
            '<initial joint="rocker_joint"',
            '<intial joint="rocker_joint"',
            "<intial>: unknown element in <scene> (it would be ignored); did you mean <initial>?",
        ),
        (
            "<scene>",
            "<scene><track kp='1' kd='1'><sine joint='crank_joint'/></track>",
            "<sine>: unknown element in <track>; valid: <sinusoid>",
        ),
        (
            "<actuator name=",
            "<jiont name='crank_joint'/><actuator name=",
            "<jiont name='crank_joint'>: unknown element in <transmission> (it would be "
            "ignored); did you mean "
            "<joint>?",
        ),
    ],
)
def test_unknown_child_of_a_closedchain_element_is_refused(fourbar_text, write, old, new, message):
    text = replaced(fourbar_text, old, new)
    path = write(text)
    with pytest.raises(
        cc.ModelFileError, match=re.escape(f"{path}: line {line_of(fourbar_text, old)}: {message}")
    ):
        cc.load(path)


def test_unknown_child_of_a_transmission_is_a_warning(fourbar_text, write, caplog):
    # Older transmissions (pr2_mechanism_model) hold <mechanicalReduction> directly.
    text = replaced(
        fourbar_text,
        "<actuator name=",
        "<mechanicalReduction>1</mechanicalReduction><actuator name=",
    )
    path = write(text)
    with caplog.at_level(logging.WARNING, logger="closedchain.urdf"):
        assert cc.load(path).actuated_joints == ("crank_joint",)
    assert f"{path}: line {line_of(text, '<mechanicalReduction>')}: <mechanicalReduction>: " in (
        caplog.text
    )


# -- names --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("old", "new", "element"),
    [
        ('<loop name="C"', '<loop name="C&#10;D"', "<loop name='C\\nD'>: the loop name"),
        (
            '<joint name="rocker_joint"',
            '<joint name="rocker&#9;joint"',
            "<joint name='rocker\\tjoint'>: the joint name",
        ),
        ('<link name="ground">', '<link name="gro&#13;und">', "<link name='gro\\rund'>: the link"),
        ('<robot name="fourbar">', '<robot name="four&#133;bar">', "<robot name='four\\x85bar'>: "),
        (
            '<transmission name="crank_transmission"',
            '<transmission name="crank&#x2028;transmission"',
            "<transmission name='crank\\u2028transmission'>: the transmission name",
        ),
    ],
)
def test_names_with_control_characters_are_refused_on_one_line(
    fourbar_text, write, old, new, element
):
    text = replaced(fourbar_text, old, new)
    path = write(text)
    with pytest.raises(cc.ModelFileError, match=re.escape(element)) as info:
        cc.load(path)
    message = str(info.value)
    assert len(message.splitlines()) == 1, message
    assert message.startswith(f"{path}: line {line_of(text, new)}: ")


@pytest.mark.parametrize("kind", ["joint", "link"])
def test_duplicate_joint_or_link_name_names_both_lines(fourbar_text, write, kind):
    """Reported as such, not blamed on the <scene> that names the lost joint."""
    duplicate, renamed = {
        "joint": ('<joint name="coupler_joint"', '<joint name="rocker_joint"'),
        "link": ('<link name="coupler">', '<link name="rocker">'),
    }[kind]
    text = replaced(fourbar_text, renamed, duplicate)
    path = write(text)
    lines = [i + 1 for i, ln in enumerate(text.splitlines()) if duplicate in ln]
    name = re.search(r'name="(\w+)"', duplicate)[1]
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(
            f"{path}: line {lines[1]}: <{kind} name={name!r}>: duplicate {kind} name, first used "
            f"at line {lines[0]}"
        ),
    ):
        cc.load(path)


# -- joint springs: <dynamics spring_stiffness spring_reference> ---------------------------

ROCKER_AXIS = """    <child link="rocker"/>
    <origin xyz="0.5 0 0" rpy="0 0 0"/>
    <axis xyz="0 -1 0"/>"""


def test_a_joint_spring_is_read(fourbar_text, write):
    dynamics = '\n    <dynamics damping="0" spring_stiffness="12.5" spring_reference="-0.25"/>'
    mech = cc.load(write(replaced(fourbar_text, ROCKER_AXIS, ROCKER_AXIS + dynamics)))
    (spring,) = mech.description.springs
    assert (spring.joint, spring.stiffness, spring.reference) == ("rocker_joint", 12.5, -0.25)


@pytest.mark.parametrize(
    "dynamics, match",
    [
        (
            'damping="0" spring_stiffness="-1"',
            "spring_stiffness='-1'>: must be a finite number >= 0",
        ),
        ('damping="0" spring_stiffness="nan"', "spring_stiffness='nan'>: must be a finite number"),
        ('damping="0" spring_reference="0.1"', "spring_reference without spring_stiffness"),
        ('spring_stiffness="1"', 'without damping or friction; add damping="0"'),
    ],
)
def test_a_bad_joint_spring_is_refused_naming_the_joint(fourbar_text, write, dynamics, match):
    path = write(replaced(fourbar_text, ROCKER_AXIS, ROCKER_AXIS + f"\n    <dynamics {dynamics}/>"))
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<joint name='rocker_joint'>") + ".*" + re.escape(match),
    ):
        cc.load(path)


def test_a_spring_on_a_continuous_joint_is_refused(fourbar_text, write):
    dynamics = '\n    <dynamics damping="0" spring_stiffness="1"/>'
    text = replaced(fourbar_text, ROCKER_AXIS, ROCKER_AXIS + dynamics)
    text = replaced(
        text,
        '<joint name="rocker_joint" type="revolute">',
        '<joint name="rocker_joint" type="continuous">',
    )
    path = write(replaced(text, '<initial joint="rocker_joint" value="-1.8151424220741028"/>', ""))
    with pytest.raises(
        cc.ModelFileError,
        match=where(path, "<joint name='rocker_joint'>")
        + ".*this joint is continuous; valid joint types: revolute, prismatic",
    ):
        cc.load(path)
