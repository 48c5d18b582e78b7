"""The law registry: discovery through entry points, and faults in plugins.

Every fault a plugin can have (it does not import, its hook raises, it declares a bad
law, its force function does not compile or returns NaN) must be reported with the
plugin's and the law's name and the reason, and must leave every other law usable.

Fake plugins are real modules written to a temporary folder on sys.path. Entry-point
discovery is exercised for real by a ``*.dist-info`` folder beside them:
importlib.metadata reads its ``entry_points.txt`` exactly as it reads an installed
package's, without the cost of a pip install.
"""

from __future__ import annotations

import importlib
import json
import re
import subprocess
import sys
import textwrap
import tomllib

import pytest

import minidem
from conftest import OBLIQUE, run_cli
from minidem.contact import declarations, laws
from minidem.results import analysis
from minidem.scene import scenario
from minidem.engine import simulation
from minidem.engine.run_loop import RunFailure

FAKE_COMMON = '''
import math

import numba

from minidem import hookimpl
from minidem.contact import ContactLaw, Parameter


@numba.njit(cache=True)
def spring_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                 normal_velocity, tangential_increment, tangential_velocity, history):
    return constants[0] * normal_overlap, 0.0, 0.0, 0.0


@numba.njit(cache=True)
def nan_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
              normal_velocity, tangential_increment, tangential_velocity, history):
    return constants[0] * normal_overlap * math.nan, 0.0, 0.0, 0.0


@numba.njit
def uncompilable_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                       normal_velocity, tangential_increment, tangential_velocity, history):
    return object(), 0.0, 0.0, 0.0


def plain_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                normal_velocity, tangential_increment, tangential_velocity, history):
    return constants[0] * normal_overlap, 0.0, 0.0, 0.0


def prepare(pair, params):
    return {"stiffness": params["stiffness"]}


def failing_prepare(pair, params):
    raise ValueError("no stiffness for these materials")


def law(name, force=spring_force, **changes):
    fields = dict(name=name, description="linear normal spring for registry tests",
                  parameters=(Parameter("stiffness", 1e8, "N/m", "normal stiffness", low=0.0, low_open=True),),
                  constants=("stiffness",), history=(), prepare=prepare, force=force, frictional=False)
    fields.update(changes)
    return ContactLaw(**fields)
'''

FAKE_PLUGINS = {
    "fake_good": '''
        @hookimpl
        def minidem_register_laws(registry):
            registry.add(law("fake_spring"))
            registry.add(law("fake_nan", force=nan_force))
            registry.add(law("fake_uncompilable", force=uncompilable_force))
            registry.add(law("fake_bad_prepare", prepare=failing_prepare))
    ''',
    "fake_bad_laws": '''
        @hookimpl
        def minidem_register_laws(registry):
            registry.add(law("fake_plain", force=plain_force))
            registry.add(law("Bad-Name"))
            registry.add(law("hmd"))
            registry.add(law("fake_bad_default", parameters=(
                Parameter("stiffness", -1.0, "N/m", "normal stiffness", low=0.0, low_open=True),)))
            registry.add(law("fake_list_parameters", parameters=[]))
            # metadata minidem laws prints, and bounds no value can pass (review of 2026-11-28:
            # a None unit took `minidem laws` down for every law)
            registry.add(law("fake_no_unit", parameters=(Parameter("stiffness", 1e8, None, "normal stiffness"),)))
            registry.add(law("fake_blank_description", parameters=(Parameter("stiffness", 1e8, "N/m", " "),)))
            registry.add(law("fake_empty_bounds", parameters=(
                Parameter("stiffness", None, "N/m", "normal stiffness", low=1e9, high=1.0),)))
            registry.add(law("fake_open_point", parameters=(
                Parameter("stiffness", None, "N/m", "normal stiffness", low=1.0, high=1.0, high_open=True),)))
            registry.add({"name": "fake_dict"})
            registry.add(law("fake_survivor"))
    ''',
    "fake_raises": '''
        @hookimpl
        def minidem_register_laws(registry):
            registry.add(law("fake_before_raise"))
            raise RuntimeError("plugin exploded while registering")
    ''',
    "fake_wrong_signature": '''
        @hookimpl
        def minidem_register_laws(registry, unknown_argument):
            registry.add(law("fake_never"))
    ''',
    "fake_import_error": '''
        import a_module_that_does_not_exist_anywhere
    ''',
    "fake_names": '''
        def _impl(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                  normal_velocity, tangential_increment, tangential_velocity, history):
            return constants[0] * normal_overlap, 0.0, 0.0, 0.0

        bound_force = numba.njit(_impl)  # the common idiom: the compiled function under another name

        @numba.njit
        def three_values_force(constants, effective_radius, effective_mass, normal_overlap,
                               normal_overlap_increment, normal_velocity, tangential_increment,
                               tangential_velocity, history):
            return constants[0] * normal_overlap, 0.0, 0.0

        @numba.njit
        def short_force(constants, effective_radius, effective_mass, normal_overlap):
            return constants[0] * normal_overlap, 0.0, 0.0, 0.0

        @numba.njit
        def old_couple_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                             normal_velocity, tangential_increment, tangential_velocity, history, relative_spin,
                             normal, dt):
            return constants[0] * normal_overlap, 0.0, 0.0, 0.0, -relative_spin[0] * dt, 0.0, 0.0

        @numba.njit
        def no_inertia_couple_force(constants, effective_radius, effective_mass, normal_overlap,
                                    normal_overlap_increment, normal_velocity, tangential_increment,
                                    tangential_velocity, history, rotation_increment, relative_spin, normal):
            return constants[0] * normal_overlap, 0.0, 0.0, 0.0, -1e-6 * relative_spin[0], 0.0, 0.0

        @numba.njit
        def couple_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                         normal_velocity, tangential_increment, tangential_velocity, history, rotation_increment,
                         relative_spin, normal, rolling_inertia):
            return constants[0] * normal_overlap, 0.0, 0.0, 0.0, -1e-6 * relative_spin[0], 0.0, 0.0

        @numba.njit
        def swapped_couple_force(constants, effective_radius, effective_mass, normal_overlap,
                                 normal_overlap_increment, normal_velocity, tangential_increment,
                                 tangential_velocity, history, rotation_increment, normal, relative_spin,
                                 rolling_inertia):
            return constants[0] * normal_overlap, 0.0, 0.0, 0.0, -1e-6 * relative_spin[0], 0.0, 0.0

        @numba.njit
        def four_value_couple_force(constants, effective_radius, effective_mass, normal_overlap,
                                    normal_overlap_increment, normal_velocity, tangential_increment,
                                    tangential_velocity, history, rotation_increment, relative_spin, normal,
                                    rolling_inertia):
            return constants[0] * normal_overlap, 0.0, 0.0, 0.0  # a couple law returns 7 numbers

        @numba.njit
        def list_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                       normal_velocity, tangential_increment, tangential_velocity, history):
            return [constants[0] * normal_overlap, 0.0, 0.0]  # a list, not a tuple (numba: a bare ValueError)

        @numba.njit
        def undefined_name_force(constants, effective_radius, effective_mass, normal_overlap,
                                 normal_overlap_increment, normal_velocity, tangential_increment,
                                 tangential_velocity, history):
            """stiffnes: the word in a docstring or a comment is not a use of the name"""
            stiffness = constants[0]  # not stiffnes
            return stiffnes * normal_overlap, 0.0, 0.0, 0.0  # noqa: F821 - the typo under test

        def prepare_from_an_unset_parameter(pair, params):
            return {"stiffness": params["derived_stiffness"]}  # None when the scenario does not set it

        def broken_contact_time(pair, constants, effective_radius, effective_mass, normal_speed):
            return constants["stifness"]  # a typo: KeyError

        def stiffness_of_a_sign_slip(pair, constants, effective_radius, effective_mass, normal_overlap):
            from minidem.contact.laws import hertz_mindlin_stiffness

            return (*hertz_mindlin_stiffness(pair, effective_radius, -normal_overlap), 0.0)  # sqrt(-d)

        @hookimpl
        def minidem_register_laws(registry):
            registry.add(law("fake_alias_thief", aliases=("HM", "fake_thief")))  # 'hm' is built in
            registry.add(law("fake_string_alias", aliases="sd"))
            registry.add(law("fake_bound", force=bound_force, aliases=("fake_b",)))
            registry.add(law("fake_three_values", force=three_values_force))
            registry.add(law("fake_short", force=short_force))
            registry.add(law("fake_old_couple", force=old_couple_force, couples=True))
            registry.add(law("fake_no_inertia_couple", force=no_inertia_couple_force, couples=True))
            registry.add(law("fake_undeclared_couple", force=couple_force))
            registry.add(law("fake_declared_plain", force=list_force, couples=True))
            registry.add(law("fake_four_value_couple", force=four_value_couple_force, couples=True))
            registry.add(law("fake_couple", force=couple_force, couples=True))
            registry.add(law("fake_swapped_couple", force=swapped_couple_force, couples=True))
            registry.add(law("fake_bad_time", contact_time=broken_contact_time))
            registry.add(law("fake_bad_stiffness", stiffness=stiffness_of_a_sign_slip))
            registry.add(law("fake_negative_time", contact_time=lambda *args: -1.0))
            registry.add(law("fake_number_time", contact_time=1e-4))
            registry.add(law("fake_none_prepare", prepare=lambda pair, params: None))
            registry.add(law("fake_list_force", force=list_force))
            registry.add(law("fake_undefined_name", force=undefined_name_force))
            registry.add(law("fake_none_constant", prepare=prepare_from_an_unset_parameter, parameters=(
                Parameter("derived_stiffness", None, "N/m", "normal stiffness, derived when not given"),)))
    ''',
    "fake_claim_a": '''
        @hookimpl
        def minidem_register_laws(registry):
            registry.add(law("fake_claimed", aliases=("fake_claimed_alias",)))
    ''',
    "fake_claim_b": '''
        @hookimpl
        def minidem_register_laws(registry):
            registry.add(law("fake_claimed"))
    ''',
    "fake_frame": '''
        @numba.njit(cache=True)
        def global_x_drag_force(constants, effective_radius, effective_mass, normal_overlap,
                                normal_overlap_increment, normal_velocity, tangential_increment,
                                tangential_velocity, history):
            # friction-like drag along the global x axis only: it depends on how the
            # scene is oriented, which no contact law may
            return constants[0] * normal_overlap, -constants[1] * tangential_velocity[0], 0.0, 0.0

        def prepare_drag(pair, params):
            return {"stiffness": params["stiffness"], "drag": params["drag"]}

        @hookimpl
        def minidem_register_laws(registry):
            registry.add(law("fake_global_x_drag", force=global_x_drag_force, prepare=prepare_drag,
                             constants=("stiffness", "drag"), frictional=True, parameters=(
                                 Parameter("stiffness", 1e8, "N/m", "normal stiffness", low=0.0, low_open=True),
                                 Parameter("friction", 0.1, "-", "unused", low=0.0),
                                 Parameter("drag", 200.0, "N s/m", "drag along x", low=0.0))))
    ''',
}


@pytest.fixture(scope="module")
def fake_site(tmp_path_factory):
    """A folder on sys.path holding the fake plugin modules (importable, not announced)."""
    site = tmp_path_factory.mktemp("site")
    for name, body in FAKE_PLUGINS.items():
        head = "" if name == "fake_import_error" else FAKE_COMMON
        (site / f"{name}.py").write_text(head + textwrap.dedent(body))
    sys.path.insert(0, str(site))
    importlib.invalidate_caches()
    yield site
    sys.path.remove(str(site))


@pytest.fixture(scope="module")
def fake_distribution(tmp_path_factory, fake_site):
    """A folder holding only ``minidem_fakeplugin-1.2.3.dist-info``: on sys.path, it makes
    importlib.metadata announce four of the fake modules as ``minidem`` entry points."""
    folder = tmp_path_factory.mktemp("dist")
    dist = folder / "minidem_fakeplugin-1.2.3.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: minidem-fakeplugin\nVersion: 1.2.3\n")
    # "bad_laws" sorts before "builtin": it must still not take the built-in 'hmd'
    (dist / "entry_points.txt").write_text(
        "[minidem]\ngood = fake_good\nbad_laws = fake_bad_laws\nraises = fake_raises\n"
        "missing = fake_import_error\n")
    return folder


@pytest.fixture
def announced(fake_distribution, monkeypatch):
    monkeypatch.syspath_prepend(str(fake_distribution))
    return fake_distribution


def load(*names):
    return laws.load_registry(extra_plugins=tuple(importlib.import_module(n) for n in names))


def broken_by_law(registry):
    return {b.law: b for b in registry.broken}


def assert_builtin_laws_run(registry):
    """The paper's HMD impact still runs from this registry (every other law still works)."""
    scene = scenario.load_scene(OBLIQUE, ["impact.angle_deg=60"])
    s = analysis.summary(simulation.Simulation(scene, registry=registry).run())
    assert s["y2"] == pytest.approx(-0.5, abs=1e-3)  # gross sliding, eq 8 with mu = 0.1


# --------------------------------------------------------------------------------------
def test_builtin_laws_come_through_minidem_entry_point():
    points = {ep.name: ep for ep in importlib.metadata.entry_points(group="minidem")}
    assert points["builtin"].value == "minidem.contact.builtin_laws"
    registry = laws.load_registry()
    for name in ("hmd", "ls", "hm", "lth", "hmdns_integral", "hmdns_integral_reset"):
        entry = registry.entry(name)
        assert (entry.plugin, entry.distribution, entry.version) == ("builtin", "minidem", minidem.__version__)
    assert not [b for b in registry.broken if b.plugin.startswith("builtin")]


def test_the_engine_imports_no_law_by_name():
    # The built-in laws reach the engine only through the registry, as a third party's do:
    # importing the engine, its kernel template and the scene loader loads none of them
    # (the kernel template once imported the linear spring as its placeholder force)
    code = ("import sys; import minidem.engine.simulation, minidem.engine.kernel, minidem.scene.scenario, "
            "minidem.geometry.neighbours; print([m for m in sys.modules if 'builtin_laws' in m])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"

def test_aliases_resolve_to_the_law():
    registry = laws.load_registry()
    assert registry.get("H-MDns").name == "hmdns_integral"  # the paper's name
    assert registry.get("HMD").name == "hmd"


def test_unknown_law_lists_the_available_ones_and_the_closest():
    with pytest.raises(laws.LawError) as info:
        laws.load_registry().get("hmdd")
    message = str(info.value)
    assert "'hmdd'" in message and "Did you mean 'hmd'?" in message
    assert "Available: " in message and "ls" in message and "lth" in message


def test_bad_declarations_are_reported_one_by_one(fake_site):
    registry = load("fake_bad_laws")
    broken = broken_by_law(registry)
    assert "numba-compiled" in broken["fake_plain"].reason
    assert "not a lower-case identifier" in broken["Bad-Name"].reason
    assert "already taken by plugin 'builtin' (minidem)" in broken["hmd"].reason
    assert "default of parameter 'stiffness'" in broken["fake_bad_default"].reason
    assert "must be > 0" in broken["fake_bad_default"].reason
    assert "tuple of minidem.contact.Parameter" in broken["fake_list_parameters"].reason
    assert "parameter 'stiffness': unit must be a non-empty string, got None" in broken["fake_no_unit"].reason
    assert "description must be a non-empty string, got ' '" in broken["fake_blank_description"].reason
    assert "bounds [1e+09, 1] admit no value" in broken["fake_empty_bounds"].reason
    assert "bounds [1, 1) admit no value" in broken["fake_open_point"].reason
    assert "expects a minidem.contact.ContactLaw (or ContactPart, Preset), got dict" in broken[None].reason
    assert all(b.plugin == "fake_bad_laws" for b in registry.broken)
    # the good law after the bad ones is kept, the built-in hmd is not displaced
    assert registry.entry("fake_survivor").plugin == "fake_bad_laws"
    assert registry.entry("hmd").plugin == "builtin"
    with pytest.raises(laws.LawError, match="fake_plain.*fake_bad_laws.*is broken.*numba"):
        registry.get("fake_plain")
    assert_builtin_laws_run(registry)


def test_a_plugin_alias_never_takes_a_builtin_name_and_aliases_are_checked(fake_site):
    registry = load("fake_names")
    broken = broken_by_law(registry)
    # 'HM' is the built-in law's name: the whole law is refused, 'hm' stays the built-in
    assert "alias 'hm' is already taken by plugin 'builtin' (minidem)" in broken["fake_alias_thief"].reason
    assert registry.entry("hm").plugin == "builtin" and registry.entry("HM").plugin == "builtin"
    with pytest.raises(laws.LawError, match="'fake_thief' from plugin 'fake_names' is broken"):
        registry.get("fake_thief")  # an alias of the refused law finds it, not a did-you-mean
    assert "'aliases' must be a tuple of names" in broken["fake_string_alias"].reason
    # a compiled function bound under another name is imported by that name
    assert declarations.force_import_name(registry.get("fake_bound")) == ("fake_names", "bound_force")
    assert "takes 4 arguments" in broken["fake_short"].reason and "tangential_velocity" in broken["fake_short"].reason
    # a couples flag that does not match the function says which it is (a plugin author's
    # review, 2026-11-28: "takes 13 arguments; the engine calls it with 9" said neither)
    assert "(the arguments of a law with couples=True: declare couples=True)" in broken["fake_undeclared_couple"].reason
    assert "couples=True is declared, which adds rotation_increment" in broken["fake_declared_plain"].reason
    # a couple law written for the earlier contract (relative_spin, normal, dt): the same
    # count, so it is recognised by its names and told what the engine passes now
    assert "now passes (rotation_increment, relative_spin, normal, rolling_inertia)" in broken["fake_old_couple"].reason
    # and one written for the contract of the morning of 2026-11-28, before the pair's
    # rolling inertia was passed (an EPSD dashpot between spheres needs it)
    assert ("takes (rotation_increment, relative_spin, normal) last" in broken["fake_no_inertia_couple"].reason
            and "rolling_inertia last" in broken["fake_no_inertia_couple"].reason)
    # two 3-tuples swapped compile and run wrong: one of the engine's names at another
    # place is refused (a plugin author's review, 2026-11-28; other names are free)
    assert ("takes 'normal' as argument 11, where the engine passes 'relative_spin' ('normal' is argument 12)"
            in broken["fake_swapped_couple"].reason)
    assert "fake_couple" not in broken
    assert "'contact_time' must be a function or None, got float" in broken["fake_number_time"].reason


def test_two_plugins_claiming_one_name_are_both_refused(fake_site):
    """Which plugin sorts first must not decide which law a scenario runs."""
    registry = load("fake_claim_a", "fake_claim_b")
    assert "fake_claimed" not in registry.names()
    refused = [b for b in registry.broken if b.law == "fake_claimed"]
    assert sorted(b.plugin for b in refused) == ["fake_claim_a", "fake_claim_b"]
    assert all("is also claimed by plugin 'fake_claim_" in b.reason and "uninstall one" in b.reason for b in refused)
    with pytest.raises(laws.LawError, match="fake_claimed.*is broken.*also claimed by plugin"):
        registry.get("fake_claimed_alias")


@pytest.mark.parametrize("order", ["ABC", "ACB", "BAC", "BCA", "CAB", "CBA"])
def test_which_plugin_loads_first_never_decides_a_name(order):
    """A = foo (alias bar), B = baz (alias bar), C = foo: every law shares a name with
    another, so none is used, in every load order (the diff review found that a law
    withdrawn from a clash left its other names to whichever plugin came later)."""
    import types

    from minidem import hookimpl

    plugins = {}
    for key, name, aliases in (("A", "foo", ("bar",)), ("B", "baz", ("bar",)), ("C", "foo", ())):
        module = types.ModuleType(f"plugin_{key}")

        def register(registry, name=name, aliases=aliases):
            registry.add(laws_module_law(name, aliases))

        module.minidem_register_laws = hookimpl(lambda registry, r=register: r(registry))
        plugins[key] = module
    registry = laws.load_registry(extra_plugins=tuple(plugins[k] for k in order))
    assert not {"foo", "bar", "baz"} & set(registry.names()), (order, registry.names())
    assert len([b for b in registry.broken if b.law in ("foo", "baz")]) == 3
    alone = laws.load_registry(extra_plugins=(plugins["A"],))  # the control: no clash, used
    assert alone.get("bar").name == "foo"


def laws_module_law(name, aliases):
    """A minimal valid law (the built-in linear spring's declaration under another name)."""
    import dataclasses

    return dataclasses.replace(laws.load_registry().get("ls"), name=name, aliases=aliases)


def test_unknown_law_names_the_plugins_that_failed_to_load(announced):
    with pytest.raises(laws.LawError) as info:
        laws.load_registry().get("a_law_of_the_missing_plugin")
    message = str(info.value)
    assert "unknown contact law" in message and re.search(r"\d plugin\(s\) failed to load", message)
    assert "'missing (minidem-fakeplugin)'" in message and "a_module_that_does_not_exist_anywhere" in message


@pytest.mark.parametrize("law_name, expected", [
    ("fake_three_values", r"three_values_force in .*fake_names\.py, line \d+ must return 4 numbers "
                          r"\(fn, ftx, fty, ftz\), it returns "),
    ("fake_bad_time", r"contact_time\(\) failed: KeyError: 'stifness' \(at .*fake_names\.py:\d+\)"),
    # raised inside minidem's helper (declarations.py): the place named is the plugin's call
    ("fake_bad_stiffness", r"stiffness\(\) failed: ValueError: math domain error \(at .*fake_names\.py:\d+\)"),
    ("fake_negative_time", r"contact_time\(\) returned -1\.0; it must be a duration in s"),
    ("fake_none_prepare", r"prepare\(\) must return a dict of constants, got NoneType"),
    # review of 2026-11-28: a list return was an internal error with an empty message, a
    # constant of None a bare TypeError naming neither (an internal error in verify)
    ("fake_list_force", r"list_force in .*fake_names\.py, line \d+ must return 4 numbers \(fn, ftx, fty, ftz\), "
                        r"it returns a list \(list\(float64\).*\): return a tuple"),
    # numba names no line for an undefined name: the line that uses it is found in the source
    ("fake_undefined_name", r"undefined_name_force in .*fake_names\.py, line (\d+) does not compile: .*name "
                            r"'stiffnes' is not defined.* \(line \d+ uses 'stiffnes'\)"),
    ("fake_none_constant", r"prepare\(\) \(prepare_from_an_unset_parameter in .*fake_names\.py, line \d+\) must "
                           r"give each constant as a number, got stiffness=None"),
    # a plugin author's review, 2026-11-28: a couple law's compile error was an internal
    # error ("Signature mismatch: 9 argument types given, but function takes 12")
    ("fake_four_value_couple", r"four_value_couple_force in .*fake_names\.py, line \d+ must return 7 numbers "
                               r"\(fn, ftx, fty, ftz, mx, my, mz: a law with couples=True\), it returns "),
])
def test_mistakes_in_a_law_are_reported_with_the_law_and_where(fake_site, monkeypatch, law_name, expected):
    registry = load("fake_names")
    with pytest.raises(laws.LawError, match=expected):
        simulation.Simulation(_fake_scene(law_name, registry, monkeypatch), registry=registry).run()


def test_verify_skips_the_sliding_limit_for_a_law_with_its_own_couple(fake_site, monkeypatch):
    # paper eqs 6-8 have only the tangential force turn the sphere: a whole law with
    # couples=True is skipped there as a combination with a rolling part is (it failed,
    # 0.38 off, a plugin author's review, 2026-11-28). Nothing is run for the skip.
    from minidem.studies import verify

    registry = load("fake_names")
    monkeypatch.setattr(laws, "registry", lambda: registry)
    (check,) = verify.Battery("fake_couple").sliding_limit()
    assert check.passed is None and check.value == "skipped: the law returns a couple (couples=True)"


def test_a_hook_that_raises_is_reported(fake_site):
    registry = load("fake_raises")
    [problem] = registry.broken
    assert problem.plugin == "fake_raises"
    assert "RuntimeError: plugin exploded while registering" in problem.reason
    assert "fake_raises.py" in problem.reason  # where it happened
    assert_builtin_laws_run(registry)


def test_a_hook_with_a_wrong_signature_is_reported(fake_site):
    registry = load("fake_wrong_signature")
    [problem] = registry.broken
    assert problem.plugin == "fake_wrong_signature"
    assert "invalid hook implementation" in problem.reason and "unknown_argument" in problem.reason
    assert "fake_never" not in registry.names()


def test_entry_point_discovery_reports_import_errors_and_keeps_the_rest(announced):
    registry = laws.load_registry()
    entry = registry.entry("fake_spring")
    assert (entry.plugin, entry.distribution, entry.version) == ("good", "minidem-fakeplugin", "1.2.3")
    [missing] = [b for b in registry.broken if b.plugin.startswith("missing")]
    assert missing.plugin == "missing (minidem-fakeplugin)"
    assert "ModuleNotFoundError" in missing.reason and "a_module_that_does_not_exist_anywhere" in missing.reason
    assert any(b.plugin == "raises" and "plugin exploded" in b.reason for b in registry.broken)
    # the built-in law keeps its name although 'bad_laws' sorts before 'builtin'
    assert registry.entry("hmd").plugin == "builtin"
    taken = [b for b in registry.broken if b.law == "hmd"]
    assert [b.plugin for b in taken] == ["bad_laws"] and "already taken by plugin 'builtin'" in taken[0].reason
    assert_builtin_laws_run(registry)


def _fake_scene(law_name, registry, monkeypatch):
    """The paper's impact with a fake law (no friction parameter)."""
    monkeypatch.setattr(laws, "_REGISTRY", registry)  # the scenario validates against it
    data = tomllib.loads(OBLIQUE.read_text())
    data["contact"] = {"law": law_name}
    data["impact"]["angle_deg"] = 0.0
    return scenario.build_scene(data, "fake.toml")


def test_a_plugin_law_runs_in_a_scenario(fake_site, monkeypatch):
    registry = load("fake_good")
    result = simulation.Simulation(_fake_scene("fake_spring", registry, monkeypatch), registry=registry).run()
    # a linear spring of 1e8 N/m on m = 0.1734 kg: contact lasts pi sqrt(m/k) (eq 27)
    m = float(result.scene.mass[0])
    s = analysis.summary(result)
    assert s["contact_duration_s"] == pytest.approx(3.14159265 * (m / 1e8) ** 0.5, rel=5e-3)
    assert s["en"] == pytest.approx(1.0, abs=1e-6)


def test_a_force_function_that_does_not_compile_names_law_and_plugin(fake_site, monkeypatch, tmp_path):
    monkeypatch.setenv("MINIDEM_CACHE_DIR", str(tmp_path))  # keep the failed kernel out of the user's cache
    registry = load("fake_good")
    sim = simulation.Simulation(_fake_scene("fake_uncompilable", registry, monkeypatch), registry=registry)
    with pytest.raises(laws.LawError) as info:
        sim.run()
    message = str(info.value)
    assert "law 'fake_uncompilable'" in message and "plugin 'fake_good'" in message
    assert "does not compile" in message and "object" in message
    monkeypatch.delenv("MINIDEM_CACHE_DIR")
    assert_builtin_laws_run(registry)


def test_a_failing_prepare_names_law_materials_and_cause(fake_site, monkeypatch):
    registry = load("fake_good")
    # the scenario file and its contact table are named too: the refused values are there
    with pytest.raises(laws.LawError, match="^fake.toml: contact: law 'fake_bad_prepare'.*prepare\\(\\) failed"
                                            ".*glass.*no stiffness"):
        simulation.Simulation(_fake_scene("fake_bad_prepare", registry, monkeypatch), registry=registry)


def test_a_nan_force_stops_the_run_at_that_step_naming_the_contact(fake_site, monkeypatch):
    registry = load("fake_good")
    sim = simulation.Simulation(_fake_scene("fake_nan", registry, monkeypatch), registry=registry)
    with pytest.raises(RunFailure) as info:
        sim.run()
    message = str(info.value)
    assert "law 'fake_nan'" in message and "non-finite force" in message
    assert "for particle 0 against walls[0] (the plane through" in message and "at step 1 " in message


def test_minidem_laws_lists_plugins_with_package_version_and_broken_ones(fake_site, fake_distribution):
    env = {"PYTHONPATH": f"{fake_site}:{fake_distribution}"}
    done = run_cli("laws", env=env)
    assert done.returncode == 0, done.stderr
    assert "fake_spring  [minidem-fakeplugin 1.2.3, plugin 'good']" in done.stdout
    assert "hmd (aliases: hertz_mindlin_deresiewicz)  [minidem 0.1.0, plugin 'builtin']" in done.stdout
    assert "BROKEN plugin 'missing (minidem-fakeplugin)': ModuleNotFoundError" in done.stdout
    assert "BROKEN plugin 'bad_laws' law 'Bad-Name'" in done.stdout
    assert "BROKEN plugin 'bad_laws' law 'fake_no_unit': parameter 'stiffness': unit must be" in done.stdout
    # every parameter's description starts in one column, at each indent (long names,
    # units such as 'N m s/rad' and integer-choice bounds pushed rows out of line)
    payload = json.loads(run_cli("laws", "--json", env=env).stdout)
    descriptions = {p["description"] for law in payload["laws"] for p in law["parameters"]}
    descriptions |= {p["description"] for part in payload["parts"] for p in part["parameters"]}
    columns: dict[int, set] = {}
    for line in done.stdout.splitlines():
        stripped = line.lstrip()
        if stripped.startswith("- "):
            found = [d for d in descriptions if d and line.endswith(d)]
            if found:
                columns.setdefault(len(line) - len(stripped), set()).add(line.index(max(found, key=len)))
    assert columns and all(len(starts) == 1 for starts in columns.values()), columns
    by_name = {law["name"]: law for law in payload["laws"]}
    assert by_name["fake_spring"]["package"] == "minidem-fakeplugin"
    assert by_name["fake_spring"]["parameters"][0] == {
        "name": "stiffness", "default": 1e8, "unit": "N/m", "bounds": "(0, inf)", "required": False,
        "description": "normal stiffness"}
    assert {"plugin": "raises", "law": None} in [{k: b[k] for k in ("plugin", "law")} for b in payload["broken"]]


def test_cli_reports_an_uncompilable_plugin_law_as_bad_input(fake_site, fake_distribution, tmp_path):
    scene_file = tmp_path / "fake.toml"
    data = OBLIQUE.read_text().replace('law = "hmd"', 'law = "fake_uncompilable"').replace("friction = 0.1", "")
    scene_file.write_text(data)
    done = run_cli("run", scene_file, "--out", tmp_path / "out",
                   env={"PYTHONPATH": f"{fake_site}:{fake_distribution}", "MINIDEM_CACHE_DIR": str(tmp_path / "cache")})
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    assert "law 'fake_uncompilable' from plugin 'good' (minidem-fakeplugin)" in done.stderr
    assert not (tmp_path / "out" / "summary.json").exists()


def test_verify_catches_a_law_that_depends_on_the_frame(fake_site, monkeypatch):
    """The negative case of `minidem verify`'s frame-invariance check: a law whose drag
    acts along the global x axis gives another collision when the scene is rotated, and
    the check must fail it (its positive case: every built-in law and the plugin of
    tests/test_faults.py pass). Momentum is still conserved: the law is equal and
    opposite on the two spheres, so only the rotation shows the defect."""
    from minidem.studies import verify

    monkeypatch.setattr(laws, "_REGISTRY", load("fake_frame"))
    checks = {c.name: c for c in verify.Battery("fake_global_x_drag").pair_collision()}
    invariance = checks["frame invariance (rotated collision)"]
    assert invariance.passed is False, invariance.value
    assert checks["sphere-sphere forces equal and opposite"].passed, checks["sphere-sphere forces equal and opposite"]



def test_bounds_print_an_unbounded_side_open_because_values_must_be_finite():
    friction = laws.Parameter("friction", None, "-", "mu", low=0.0, required=True)
    stiffness = laws.Parameter("stiffness", None, "N/m", "k", low=0.0, low_open=True)
    assert friction.bounds_text() == "[0, inf)"
    assert stiffness.bounds_text() == "(0, inf)"
    assert laws.Parameter("x", 0.0, "-", "x").bounds_text() == "(-inf, inf)"
    assert laws.Parameter("e", 1.0, "-", "e", low=0.0, high=1.0, low_open=True).bounds_text() == "(0, 1]"
    assert friction.check(float("inf")) == "must be finite, got inf"
    # hmd's special_case takes integers only, and says so wherever its bounds are printed
    special = laws.registry().get("hmd").parameter("special_case")
    assert special.bounds_text() == "one of the integers 0..5"
    assert special.check(2.5) == "must be one of the integers 0..5, got 2.5"
    assert special.check(3) is None


def test_a_plugin_whose_hook_pluggy_ignores_is_reported_not_silently_missing(tmp_path, monkeypatch):
    # pluggy ignores a hook function without @minidem.hookimpl, and keeps a marked one of
    # a misspelt name aside: either way the plugin's laws were silently missing, and the
    # run said only "unknown contact law" (found by a plugin author's walk-through)
    body = ("from minidem import hookimpl\n\n"
            "{mark}def {name}(registry):\n    raise AssertionError('never called')\n")
    modules = {"fake_unmarked": ("", "minidem_register_laws"), "fake_misspelt": ("@hookimpl\n", "minidem_register_law"),
               "fake_hookless": ("", "setup")}
    for module, (mark, name) in modules.items():
        (tmp_path / f"{module}.py").write_text(body.format(mark=mark, name=name))
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = load(*modules)
    reasons = {b.plugin: b.reason for b in registry.broken}
    assert "decorate it with @minidem.hookimpl" in reasons["fake_unmarked"]
    assert "defines minidem_register_law, not the hook minidem_register_laws" in reasons["fake_misspelt"]
    assert "defines no minidem_register_laws hook" in reasons["fake_hookless"]
    assert registry.entry("hmd").plugin == "builtin"  # the others are untouched


def test_a_combination_names_each_package_with_its_version():
    # the run's header and summary.json's law_package: "minidem + minidem-kk-parts 0.1.0 +
    # 1.0.0" read as two lists to match up (plugin author's review, 2026-11-28)
    law = laws.load_registry().get("hmd")
    combined = laws.RegisteredLaw(law, "builtin + kk", "minidem + minidem-kk-parts", "0.1.0 + 1.0.0")
    assert combined.packages == "minidem 0.1.0 + minidem-kk-parts 1.0.0"
    assert laws.load_registry().entry("hmd").packages.startswith("minidem ")
