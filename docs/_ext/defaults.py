"""MkDocs hook: state the default configuration of ``simulate`` from the code's constants.

A page writes ``{{ default_configuration }}`` (a sentence, for prose) or
``{{ default_configuration_short }}`` (a few words, for a code comment); this hook
(listed under ``hooks:`` in mkdocs.yml) replaces them, at build time, with text made from
``DEFAULT_METHOD``, ``DEFAULT_INTEGRATOR`` and its registry entry (tolerances, default
stabilization), ``SimulationSettings``' first trial step and ``DEFAULT_ENERGY_TOL``: the
pages cannot state another default than the one that runs. README.md, which is not built,
is checked against :func:`short` by tests/test_docs.py.
"""

from __future__ import annotations

from typing import Any

from closedchain.dynamics import DEFAULT_METHOD
from closedchain.simulate import (
    DEFAULT_ENERGY_TOL,
    DEFAULT_INTEGRATOR,
    DEFAULT_SIMULATION_SETTINGS,
    INTEGRATORS,
)
from closedchain.simulate.request import describe_default
from closedchain.simulate.request import short_number as _num

#: Placeholders and the functions that fill them.
PLACEHOLDERS = ("{{ default_configuration }}", "{{ default_configuration_short }}")

_MS_PER_S = 1e3


def short() -> str:
    """The default configuration in a few words: method, integrator at its tolerances,
    stabilization."""
    return describe_default()


def sentence() -> str:
    """The default configuration as the call that runs it, with what each part means."""
    spec = INTEGRATORS[DEFAULT_INTEGRATOR]
    tolerances = ""
    if spec.tolerances:
        rtol, atol = spec.tolerances
        tolerances = f", rtol={_num(rtol)}, atol={_num(atol)}"
    first_step = (
        f", first trial step {DEFAULT_SIMULATION_SETTINGS.dt * _MS_PER_S:g} ms"
        if spec.kind == "adaptive"
        else f", dt={DEFAULT_SIMULATION_SETTINGS.dt:g} s"
    )
    return (
        f'**`method="{DEFAULT_METHOD}", integrator="{spec.name}"{tolerances}, '
        f'stabilization="{spec.default_stabilization}"`** ({spec.kind} step{first_step}; '
        f"{spec.description}), with the energy balance checked to "
        f"`energy_tol={_num(DEFAULT_ENERGY_TOL)}`"
    )


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    """MkDocs event: fill the placeholders of a page's Markdown."""
    return markdown.replace(PLACEHOLDERS[0], sentence()).replace(PLACEHOLDERS[1], short())
