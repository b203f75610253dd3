"""Foam parameters: named presets, scene overrides and parameter files (DiffuseCalculator-style
keys, and the VisualSPHysics foam simulator's .ini that DualSPHysics users have)."""

from __future__ import annotations

import configparser
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Foam
from ..errors import InputError
from ..progress import console

# SPlisHSPlasH FoamGenerator's --foamscale default (Tools/FoamGenerator/main.cpp): the global
# multiplier of the generated count; its automatic mode sets k_ta = k_wc = 1 times this.
FOAMSCALE = 1000.0
# whitecap's own foam thinning [1/s] (its presets and 'auto'; [foam] foam_dissipation): each foam
# particle also vanishes at this rate, so long-lived foam does not pile up. FoamGenerator has no
# such term, so its presets set 0.
FOAM_DISSIPATION = 0.5


@dataclass(frozen=True)
class FoamParams:
    """Resolved parameters of Ihmsen et al. 2012 (SI units): what :func:`resolve` makes of a preset,
    a parameter file and the scene's ``[foam]`` section.

    No field has a default here: each value's meaning, unit, bounds and default are those of the
    ``[foam]`` field of the same name (:class:`whitecap.config.Foam`), or, for the fields that section
    leaves unset, the preset's (:data:`PRESETS`). The ``[foam]`` fields in :data:`MADE_FROM` reach the
    parameters in another form."""

    # From the preset unless [foam] or the .ini sets them.
    ta_min: float  # trapped air τ [m/s]
    ta_max: float
    wc_min: float  # wave crest τ [-]
    wc_max: float
    ke_min: float  # kinetic energy per unit mass τ [J/kg]
    ke_max: float
    vo_min: float  # vorticity τ [1/s]
    vo_max: float
    k_ta: float  # generation rate multipliers [1/s]
    k_wc: float
    k_vo: float
    spray_below: int  # fluid-neighbour count thresholds
    bubble_above: int
    lifetime_min: float  # [s]
    lifetime_max: float
    lifetime_multiplier: float  # > 0: lifetime = multiplier · I_k · Δt
    buoyancy: float  # k_b
    drag: float  # k_d
    foam_dissipation: float  # [1/s]: foam vanishes at this rate besides its lifetime
    wall_correction: bool  # 'foamgenerator' model: FoamGenerator's --bbsize count correction (.splishsplash)
    # 'ihmsen2012': whitecap's potentials (kernel W̃ = 1 − r/h, E_k per unit mass [J/kg]);
    # 'foamgenerator': SPlisHSPlasH FoamGenerator's automatic mode (see .splishsplash).
    model: str
    # From [foam] as given.
    budget: float  # 'auto': diffuse per fluid particle at the peak
    radius: float  # × fluid radius
    support: float  # × fluid radius
    slots_per_particle: int | None  # at most this many new particles per fluid particle and frame
    max_particles: int | None  # None: budget.capacity_for (a little over budget × fluid particles)
    spray_lifetime: tuple | None  # (min, max) [s]; None: no countdown while spray
    bubble_lifetime: tuple | None  # (min, max) [s]; None: no countdown while a bubble
    # Made from [foam]'s other fields (MADE_FROM).
    shares: tuple  # 'auto': spray, foam, bubbles' parts of the budget (sum 1)
    type_multipliers: tuple  # spray, foam, bubbles: generation of each type, relative
    auto: bool  # preset 'auto'
    explicit: frozenset  # names set in [foam] or the .ini: 'auto' leaves them alone


#: The ``[foam]`` fields that reach :class:`FoamParams` in another form, and the fields made of
#: them; every other field of the section is a field of the parameters under its own name.
MADE_FROM: dict[str, tuple[str, ...]] = {
    "enabled": (),  # whether the foam stage runs at all, not a parameter of it
    "preset": ("auto", "model"),  # and the starting value of every field it sets (PRESETS)
    "shares": ("shares",),  # normalised to sum 1
    "spray_multiplier": ("type_multipliers",),
    "foam_multiplier": ("type_multipliers",),
    "bubble_multiplier": ("type_multipliers",),
}
#: What every preset has unless it says otherwise: whitecap's potentials, and no FoamGenerator box.
PRESET_BASE = dict(model="ihmsen2012", wall_correction=False)

PRESETS: dict[str, dict] = {
    # Ihmsen, Akinci, Akinci & Teschner 2012, "Unified spray, foam and air bubbles for particle-based fluids".
    "ihmsen2012": dict(
        ta_min=5, ta_max=20, wc_min=2, wc_max=8, ke_min=5, ke_max=50, vo_min=5, vo_max=20,
        k_ta=4000, k_wc=50000, k_vo=0, spray_below=6, bubble_above=20,
        lifetime_min=2, lifetime_max=5, lifetime_multiplier=0, buoyancy=2.0, drag=0.8,
        foam_dissipation=FOAM_DISSIPATION,
    ),
    # DualSPHysics DiffuseCalculator defaults.
    "dualsphysics": dict(
        ta_min=5, ta_max=20, wc_min=2, wc_max=8, ke_min=5, ke_max=50, vo_min=5, vo_max=20,
        k_ta=40, k_wc=40, k_vo=0, spray_below=6, bubble_above=9,
        lifetime_min=0, lifetime_max=0, lifetime_multiplier=10, buoyancy=0.8, drag=0.5,
        foam_dissipation=FOAM_DISSIPATION,
    ),
    # SPlisHSPlasH FoamGenerator's manual-mode numbers (its --no-auto defaults for --limits,
    # --ta, --wc, --vo, --lifetime, --buoyancy, --drag), applied to whitecap's potentials
    # and without its --foamscale: not what FoamGenerator does by default.
    "splishsplash-manual": dict(
        ta_min=5, ta_max=20, wc_min=2, wc_max=8, ke_min=5, ke_max=50, vo_min=5, vo_max=20,
        k_ta=4000, k_wc=50000, k_vo=4000, spray_below=6, bubble_above=20,
        lifetime_min=2, lifetime_max=5, lifetime_multiplier=0, buoyancy=2.0, drag=0.8,
        foam_dissipation=0.0,  # FoamGenerator's foam goes only when its lifetime ends
    ),
    # SPlisHSPlasH FoamGenerator's default, automatic mode: limits from the whole sequence
    # (τmin, τmax = 0.1, 1 × the mean per-frame maximum; the values below are placeholders),
    # factors 1 × foamscale 1000, cubic spline potentials, vorticity off (see .splishsplash).
    "splishsplash": dict(
        ta_min=0, ta_max=1, wc_min=0, wc_max=1, ke_min=0, ke_max=1, vo_min=0, vo_max=1,
        k_ta=FOAMSCALE, k_wc=FOAMSCALE, k_vo=0, spray_below=6, bubble_above=20,
        lifetime_min=2, lifetime_max=5, lifetime_multiplier=0, buoyancy=2.0, drag=0.8, model="foamgenerator",
        foam_dissipation=0.0,  # FoamGenerator's foam goes only when its lifetime ends
    ),
}
# FoamGenerator's default run with --bbsize = the domain and --bbtype kill: its count correction
# for foam near the box's faces as well (see .splishsplash).
PRESETS["splishsplash-box"] = dict(PRESETS["splishsplash"], wall_correction=True)
PRESETS["auto"] = dict(PRESETS["ihmsen2012"])

# DiffuseCalculator-style keys -> our names (case-insensitive, in any section but the job
# sections below). Energies here are per unit mass [J/kg], as in [foam].
INI_KEYS = {
    "tamin": "ta_min", "tamax": "ta_max", "wcmin": "wc_min", "wcmax": "wc_max",
    "kemin": "ke_min", "kemax": "ke_max", "kta": "k_ta", "kwc": "k_wc",
    "spraymax": "spray_below", "spraythreshold": "spray_below", "bubblemin": "bubble_above",
    "bubblethreshold": "bubble_above", "lifetimemultiplier": "lifetime_multiplier", "lifetime": "lifetime_multiplier",
    "buoyancy": "buoyancy", "kb": "buoyancy", "drag": "drag", "kd": "drag",
}
# The VisualSPHysics foam simulator's [FOAMPARAMETERS] (the .ini DualSPHysics users have).
# Its kinetic-energy thresholds are ½ m |v|² of one particle [J]; they are divided by the
# case's particle mass (XmlFile's massfluid) to give ours per unit mass.
FOAM_KEYS = {
    "mintrappedairthreshold": "ta_min", "maxtrappedairthreshold": "ta_max",
    "minwavecreststhreshold": "wc_min", "maxwavecreststhreshold": "wc_max",
    "minkineticenergythreshold": "ke_min", "maxkineticenergythreshold": "ke_max",
    "maxkineticpowerthreshold": "ke_max",  # the spelling of the DualSPHysics-to-Blender example
    "diffusetrappedairmultiplier": "k_ta", "diffusewavecrestsmultiplier": "k_wc",
    "spraydensity": "spray_below", "bubblesdensity": "bubble_above",  # fluid-neighbour counts
    "lifefimemultiplier": "lifetime_multiplier",  # sic, as the simulator spells it
    "buoyancycontrol": "buoyancy", "dragcontrol": "drag",
}
JOULE_KEYS = {"minkineticenergythreshold", "maxkineticenergythreshold", "maxkineticpowerthreshold"}
INT_PARAMS = ("spray_below", "bubble_above")
# The job sections of that file: what to read, which frames, where to write, the domain.
JOB_KEYS = {
    "paths": ("InputDataPath", "InputFilesPrefix", "ZeroPadding", "OutputDataPath", "FilesOutputPrefix",
              "ExclusionZoneFile", "XmlFile"),
    "timesteps": ("StartingTimeStep", "EndingTimeStep"),
    "output": ("TextFiles", "PlyFiles", "VtkFiles", "VtkDiffuseData", "VtkFluidData"),
    "domain": ("CustomDomain", "DomainMinx", "DomainMiny", "DomainMinz", "DomainMaxx", "DomainMaxy", "DomainMaxz"),
}


@dataclass(frozen=True)
class IniJob:
    """The job a VisualSPHysics foam .ini describes; relative paths are from the file's folder."""

    input_dir: Path | None = None
    prefix: str = ""
    zero_padding: int = 4
    first: int | None = None
    last: int | None = None
    out: Path | None = None
    out_prefix: str = ""
    exclusion_zone: str = ""
    xml: Path | None = None
    domain: tuple | None = None  # (lower, upper) when CustomDomain
    outputs: tuple = ()  # [OUTPUT] formats asked for (whitecap writes PLY; see `whitecap export`)

    def frame_path(self, i: int) -> Path:
        """InputDataPath / InputFilesPrefix + the frame number, at least ZeroPadding digits, + .vtk."""
        assert self.input_dir is not None, "a job's frames need [PATHS] InputDataPath"
        return self.input_dir / f"{self.prefix}{i:0{self.zero_padding}d}.vtk"


@dataclass(frozen=True)
class IniFile:
    path: Path
    params: dict  # our names -> values (energies per unit mass)
    joules: dict  # ke_min / ke_max given per particle [J], to divide by the particle mass
    job: IniJob | None  # None unless the file has job sections ([PATHS], [TIMESTEPS], [DOMAIN])
    unknown: tuple  # "[SECTION] Key" of every key not understood


def resolve(cfg: Foam | None = None, ini: str | Path | IniFile | None = None, preset: str | None = None,
            particle_mass: float | None = None) -> FoamParams:
    """Preset, then .ini values, then every value set in the scene's [foam] section.

    ``particle_mass`` [kg] converts a VisualSPHysics file's kinetic-energy thresholds
    (joules per particle) to ours (per unit mass)."""
    cfg = cfg or Foam()
    name = preset or cfg.preset
    if name not in PRESETS:
        raise InputError(f"foam.preset: unknown preset {name!r} (known: {', '.join(PRESETS)})")
    values = dict(PRESET_BASE, **PRESETS[name])
    explicit: set[str] = set()
    if ini is not None:
        f = ini if isinstance(ini, IniFile) else read_ini(ini)
        values.update(f.params)
        explicit |= set(f.params) | set(f.joules)
        if f.joules:
            key = next(iter(f.joules.values()))[0]
            if not particle_mass or particle_mass <= 0:
                raise InputError(f"{f.path}: {key} is the energy of one particle [J] and the particle mass is "
                                 "unknown; give the case XML ([PATHS] XmlFile or --case)")
            values.update({ours: v / particle_mass for ours, (_, v) in f.joules.items()})
    for field_name, v in cfg:  # every other [foam] field is a parameter of the same name
        if field_name in MADE_FROM or (v is None and field_name in values):  # unset: the preset's or the .ini's
            continue
        values[field_name] = tuple(v) if isinstance(v, list) else v
        if field_name in PRESETS[name]:
            explicit.add(field_name)
    values["type_multipliers"] = (cfg.spray_multiplier, cfg.foam_multiplier, cfg.bubble_multiplier)
    values["shares"] = tuple(float(x) / sum(cfg.shares) for x in cfg.shares)
    values["auto"] = name == "auto"
    values["explicit"] = frozenset(explicit)
    p = FoamParams(**values)
    for lo, hi in (("ta_min", "ta_max"), ("wc_min", "wc_max"), ("ke_min", "ke_max"), ("vo_min", "vo_max")):
        if getattr(p, hi) <= getattr(p, lo):
            raise InputError(f"foam.{hi}: must be greater than foam.{lo} ({getattr(p, hi)} <= {getattr(p, lo)})")
    if p.bubble_above < p.spray_below:
        raise InputError("foam.bubble_above: must not be below foam.spray_below")
    return p


class _SpelledParser(configparser.ConfigParser):
    """A ConfigParser that keeps the keys' spelling (for messages); lookups are case-folded by the reader."""

    def optionxform(self, optionstr: str) -> str:
        return optionstr


def read_ini(path: str | Path) -> IniFile:
    """A DiffuseCalculator-style parameter file or a VisualSPHysics foam-simulator .ini.

    Bad values raise a one-line InputError naming the file, section and key;
    keys not understood are listed in one warning line."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: parameter file not found")
    cp = _SpelledParser(inline_comment_prefixes=("#", ";"), strict=False, interpolation=None)
    try:
        text = p.read_text()
        if not text.lstrip().startswith("["):
            text = "[diffuse]\n" + text
        cp.read_string(text)
    except (configparser.Error, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: not a readable .ini file ({' '.join(str(exc).split())})") from None

    def where(sec: str, key: str) -> str:
        return f"{p}: [{sec}] {key}"

    params: dict = {}
    joules: dict = {}
    job_raw: dict[str, dict[str, tuple[str, str]]] = {}
    unknown: list[str] = []
    for sec in cp.sections():
        sl = sec.lower()
        for key in cp[sec]:
            val = cp[sec][key].strip()
            kl = key.replace("_", "").lower()
            if sl in JOB_KEYS:
                if kl in {k.lower() for k in JOB_KEYS[sl]}:
                    job_raw.setdefault(sl, {})[kl] = (where(sec, key), val)
                else:
                    unknown.append(f"[{sec}] {key}")
                continue
            ours = FOAM_KEYS.get(kl) or INI_KEYS.get(kl)
            if ours is None:
                unknown.append(f"[{sec}] {key}")
                continue
            try:
                num = float(val)
            except ValueError:
                raise InputError(f"{where(sec, key)}: expected a number, got {val!r}") from None
            if not np.isfinite(num) or num < 0:
                raise InputError(f"{where(sec, key)}: expected a finite number >= 0, got {val!r}")
            if kl in JOULE_KEYS:
                joules[ours] = (where(sec, key), num)
                params.pop(ours, None)
            else:
                params[ours] = int(num) if ours in INT_PARAMS else num
                joules.pop(ours, None)
    job = _read_job(p, job_raw) if job_raw else None
    if not params and not joules and job is None:
        raise InputError(f"{p}: no known parameters (e.g. [FOAMPARAMETERS] MinTrappedAirThreshold, or TaMin, KTa)")
    if unknown:
        console.print(
            f"[yellow]warning:[/] {p}: {len(unknown)} key(s) not understood, ignored: {', '.join(unknown)}",
            soft_wrap=True,
        )
    return IniFile(p, params, joules, job, tuple(unknown))


def _read_job(p: Path, raw: dict) -> IniJob:
    """The [PATHS], [TIMESTEPS], [OUTPUT] and [DOMAIN] sections as an IniJob."""
    def get(sec: str, key: str) -> tuple[str, str] | None:
        return raw.get(sec, {}).get(key.lower())

    def named(sec: str, key: str) -> str:
        """'file: [SECTION] Key' of a key the file gives."""
        v = get(sec, key)
        assert v is not None
        return v[0]

    def text(sec, key) -> str:
        v = get(sec, key)
        return v[1] if v else ""

    def path(sec, key) -> Path | None:
        v = text(sec, key)
        return Path(os.path.normpath(p.parent / Path(v).expanduser())) if v else None

    def integer(sec, key) -> int | None:
        v = get(sec, key)
        if v is None or v[1] == "":
            return None
        try:
            return int(v[1])
        except ValueError:
            raise InputError(f"{v[0]}: expected a whole number, got {v[1]!r}") from None

    def number(sec, key) -> float:
        v = get(sec, key)
        if v is None or v[1] == "":
            raise InputError(f"{p}: [DOMAIN] {key}: missing (needed with CustomDomain = yes)")
        try:
            x = float(v[1])
        except ValueError:
            raise InputError(f"{v[0]}: expected a number, got {v[1]!r}") from None
        if not np.isfinite(x):
            raise InputError(f"{v[0]}: expected a finite number, got {v[1]!r}")
        return x

    def boolean(sec, key) -> bool:
        v = get(sec, key)
        if v is None or v[1] == "":
            return False
        b = configparser.ConfigParser.BOOLEAN_STATES.get(v[1].lower())
        if b is None:
            raise InputError(f"{v[0]}: expected yes or no, got {v[1]!r}")
        return b

    pad = integer("paths", "ZeroPadding")
    if pad is not None and not 0 <= pad <= 12:
        raise InputError(f"{named('paths', 'ZeroPadding')}: expected 0 to 12 digits, got {pad}")
    first, last = integer("timesteps", "StartingTimeStep"), integer("timesteps", "EndingTimeStep")
    if first is not None and first < 0:
        raise InputError(f"{named('timesteps', 'StartingTimeStep')}: expected a frame number >= 0, got {first}")
    if first is not None and last is not None and last < first:
        raise InputError(f"{named('timesteps', 'EndingTimeStep')}: {last} is before StartingTimeStep {first}")
    domain = None
    if boolean("domain", "CustomDomain"):
        lo = [number("domain", f"DomainMin{a}") for a in "xyz"]
        hi = [number("domain", f"DomainMax{a}") for a in "xyz"]
        for a, l_, h_ in zip("xyz", lo, hi):
            if h_ <= l_:
                raise InputError(f"{p}: [DOMAIN] DomainMax{a}: must be greater than DomainMin{a} ({h_} <= {l_})")
        domain = (lo, hi)
    outputs = tuple(k for k in JOB_KEYS["output"] if boolean("output", k))
    return IniJob(
        input_dir=path("paths", "InputDataPath"), prefix=text("paths", "InputFilesPrefix"),
        zero_padding=4 if pad is None else pad, first=first, last=last, out=path("paths", "OutputDataPath"),
        out_prefix=text("paths", "FilesOutputPrefix"), exclusion_zone=text("paths", "ExclusionZoneFile"),
        xml=path("paths", "XmlFile"), domain=domain, outputs=outputs,
    )


