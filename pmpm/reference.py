"""Analytic and published references used by the validation tests and benchmark scripts."""
from __future__ import annotations

import numpy as np


def stokes_velocity(x: np.ndarray, center: np.ndarray, radius: float, far_velocity: np.ndarray) -> np.ndarray:
    """Stokes (1851) creeping flow past a fixed sphere, uniform ``far_velocity`` far away (n, 3)."""
    r_vec = np.asarray(x, float) - center
    r = np.linalg.norm(r_vec, axis=1)[:, None]
    along = (r_vec @ far_velocity)[:, None]
    return (far_velocity - 0.75 * radius * (far_velocity / r + along * r_vec / r ** 3)
            - 0.25 * radius ** 3 * (far_velocity / r ** 3 - 3 * along * r_vec / r ** 5))


def stokes_drag(viscosity: float, radius: float, speed: float) -> float:
    """6 π μ a U (N)."""
    return 6 * np.pi * viscosity * radius * speed


def rotlet_torque(viscosity: float, radius: float, omega: float) -> float:
    """Torque on a sphere spinning in unbounded still fluid at low Re, 8 π μ a³ ω (N m)."""
    return 8 * np.pi * viscosity * radius ** 3 * omega


def schiller_naumann_drag_coefficient(reynolds):
    """C_D = 24/Re (1 + 0.15 Re^0.687), Re < 800."""
    reynolds = np.asarray(reynolds, float)
    return 24.0 / reynolds * (1 + 0.15 * reynolds ** 0.687)


def standard_drag_coefficient(reynolds):
    """The standard drag curve of a sphere: Schiller–Naumann up to Re 800, beyond it Clift, Grace &
    Weber's (1978, Bubbles, Drops and Particles, Table 5.2) fits for 260–1500 and 1500–12000.
    Schiller–Naumann itself lies within about ±5 % of the measurements it was fitted to."""
    reynolds = np.asarray(reynolds, float)
    w = np.log10(reynolds)
    return np.where(reynolds <= 800, schiller_naumann_drag_coefficient(reynolds),
                    np.where(reynolds <= 1500, 10 ** (1.6435 - 1.1242 * w + 0.1558 * w ** 2),
                             10 ** (-2.4571 + 2.5558 * w - 0.9295 * w ** 2 + 0.1049 * w ** 3)))


def oseen_velocity(x: np.ndarray, center: np.ndarray, radius: float, far_velocity: np.ndarray,
                   kinematic_viscosity: float, drag_coefficient: float) -> np.ndarray:
    """Oseen's (1910) flow past a fixed sphere in Lamb's form (Hydrodynamics, §342), with the wake's
    strength set by ``drag_coefficient``: u = U + ∇φ + ∇χ/(2k) − χ e, k = |U|/(2ν),
    χ = B e^{k(x − r)}/r, φ = −(a³|U|/4) x/r³ − B/(2k r), B = F/(4πμ), x = r·e along the stream e.
    It is the far field of any steady flow past a body of drag F (an Oseenlet, the source that feeds
    its wake, and the potential dipole), and Stokes' far field as Re → 0 (B = 3a|U|/2). (n, 3)."""
    far_velocity = np.asarray(far_velocity, float)
    speed = float(np.linalg.norm(far_velocity))
    e = far_velocity / speed
    k = speed / (2 * kinematic_viscosity)
    strength = drag_coefficient * speed ** 2 * radius ** 2 / (8 * kinematic_viscosity)   # B
    r_vec = np.asarray(x, float) - center
    r = np.linalg.norm(r_vec, axis=1)[:, None]
    along = (r_vec @ e)[:, None]
    unit = r_vec / r
    wake = np.exp(k * (along - r))                 # ≤ 1: x ≤ r
    chi = strength * wake / r
    return (far_velocity - 0.25 * radius ** 3 * speed * (e / r ** 3 - 3 * along * r_vec / r ** 5)
            + strength * (1 - wake) / (2 * k * r ** 2) * unit - 0.5 * chi * (e + unit))


def square_duct_wall_factor(diameter_over_side: float) -> float:
    """Creeping-flow drag factor K of a sphere on the axis of a square duct, to first order in
    λ = d / side: K = 1 / (1 − 1.903 λ) (Haberman's coefficient, as tabulated by Happel & Brenner,
    Low Reynolds Number Hydrodynamics; the circular tube's is 2.104)."""
    return 1.0 / (1.0 - 1.903 * diameter_over_side)


def terminal_velocity(particle_density, fluid_density, viscosity, diameter, gravity=9.81, wall_factor=1.0):
    """Terminal settling speed with the Schiller–Naumann drag times ``wall_factor``, by
    fixed-point iteration on Re."""
    weight = (particle_density - fluid_density) * np.pi * diameter ** 3 / 6 * gravity
    speed = abs(weight) / (3 * np.pi * viscosity * diameter * wall_factor)          # Stokes first guess
    for _ in range(200):
        reynolds = fluid_density * speed * diameter / viscosity
        cd = wall_factor * schiller_naumann_drag_coefficient(reynolds)
        speed = np.sqrt(abs(weight) / (0.5 * fluid_density * cd * np.pi * diameter ** 2 / 4))
    return speed


def di_felice_wall_factor(diameter_ratio: float, reynolds: float) -> float:
    """Settling speed in a tube over that in unbounded fluid, ((1 − λ)/(1 − 0.33 λ))^a with
    a = (3.3 + 0.085 Re)/(1 + 0.1 Re), λ = sphere over tube diameter (Di Felice 1996, fitted to
    measurements for Re from 0.01 to 200)."""
    exponent = (3.3 + 0.085 * reynolds) / (1 + 0.1 * reynolds)
    return ((1 - diameter_ratio) / (1 - 0.33 * diameter_ratio)) ** exponent


# ten Cate, Nieuwstad, Derksen & Van den Akker (2002), "Particle imaging velocimetry experiments and
# lattice-Boltzmann simulations on a single sphere settling under gravity", Phys. Fluids 14, 4012,
# Table 1: a nylon sphere (d = 15 mm, ρ = 1120 kg/m³) released from rest with its centre 127.5 mm
# above the floor of a closed box 100 × 100 × 160 mm of silicone oil. Per experiment: fluid density
# (kg/m³), viscosity (Pa s), and the measured terminal (largest) settling speed (m/s).
TEN_CATE_2002 = {
    "E1": (970.0, 0.373, 0.038),   # Re 1.5
    "E2": (965.0, 0.212, 0.060),   # Re 4.1
    "E3": (962.0, 0.113, 0.091),   # Re 11.6
    "E4": (960.0, 0.058, 0.128),   # Re 31.9
}
TEN_CATE_BOX = (0.100, 0.100, 0.160)      # m, the sphere released on the vertical axis
TEN_CATE_SPHERE = (0.015, 1120.0, 0.1275)  # diameter (m), density (kg/m³), release height of the centre (m)

# The same spheres and liquids settling through an infinite duct of ten Cate's cross-section, solved
# body-fitted by OpenFOAM v1912 (bench/openfoam_sphere_duct.sh: a held sphere, walls and inflow moving
# at U, simpleFoam on a snappyHexMesh mesh with 24 cells per diameter on the sphere; the terminal speed
# interpolated between the drags at two speeds, bench/accuracy.py --settling, 2026-11-23). Refining the
# sphere's surface to 48 cells per diameter raises the drag by 0.6 % (E1) and 0.5 % (E4), which lowers
# these by 0.6 % and 0.3 %.
# A closed box as tall as ten Cate's settles within 0.6 % of a box 2.5 times taller (pmpm, E1 and E4),
# so these are the terminal speeds of the Navier–Stokes equations in their box, to about 1 %. The
# measured speeds (TEN_CATE_2002) are 4–9 % above them.
TEN_CATE_BODY_FITTED = {"E1": 0.0351, "E2": 0.0581, "E3": 0.0881, "E4": 0.1234}   # m/s


def beverloo_mass_rate(orifice_diameter, particle_diameter, bulk_density, gravity=9.81, c=0.58, k=1.5):
    """Beverloo's law for the steady discharge of coarse, free-flowing grains from a flat-bottomed
    bin through a circular orifice (kg/s): W = C ρ_b √g (D₀ − k d)^{5/2}, independent of the fill
    height. C = 0.58 and k = 1.5 are Beverloo, Leniger & van de Velde's (1961, Chem. Eng. Sci. 15,
    260) fit over their materials (C ranged 0.55–0.65), for D₀ ≳ 6 d. A conical hopper no steeper
    than the stagnant zone that forms over a flat bottom discharges as the flat-bottomed bin;
    a steeper one faster (Rose & Tanaka's factor, reviewed by Nedderman, Tüzün, Savage & Houlsby
    1982, Chem. Eng. Sci. 37, 1597)."""
    return c * bulk_density * np.sqrt(gravity) * (orifice_diameter - k * particle_diameter) ** 2.5


# ----------------------------------------------------------------------------------------------
# Dense suspensions: packed and fluidized beds of equal spheres (superficial velocity U, voidage ε)
# ----------------------------------------------------------------------------------------------
def ergun_pressure_drop(superficial_velocity, porosity, diameter, fluid_density, viscosity):
    """Pressure drop per unit length of a packed bed of spheres, −dp/dz (Pa/m), Ergun (1952, Chem.
    Eng. Prog. 48, 89):

        −dp/dz = 150 μ U (1 − ε)² / (ε³ d²) + 1.75 ρ U² (1 − ε) / (ε³ d).

    Fitted to measurements over Re = ρ U d/μ from ≈ 1 to several thousand; the data scatter by
    about ±20 % about it (Macdonald et al. 1979 refit 180 and 1.8 for smooth spheres)."""
    u, e = np.asarray(superficial_velocity, float), np.asarray(porosity, float)
    return (150.0 * viscosity * u * (1 - e) ** 2 / (e ** 3 * diameter ** 2)
            + 1.75 * fluid_density * u * np.abs(u) * (1 - e) / (e ** 3 * diameter))


def archimedes_number(particle_density, fluid_density, viscosity, diameter, gravity=9.81):
    """Ar = ρf (ρp − ρf) g d³ / μ²."""
    return fluid_density * (particle_density - fluid_density) * gravity * diameter ** 3 / viscosity ** 2


def wen_yu_minimum_fluidization(particle_density, fluid_density, viscosity, diameter, gravity=9.81):
    """Minimum fluidization velocity (m/s), Wen & Yu (1966, AIChE J. 12, 610): Ergun at the onset
    with 1/(φ ε_mf³) ≈ 14 and (1 − ε_mf)/(φ² ε_mf³) ≈ 11 (ε_mf ≈ 0.38–0.42 for spheres),

        Re_mf = √(33.7² + 0.0408 Ar) − 33.7;

    its fit to 284 measurements scatters by about ±34 %."""
    ar = archimedes_number(particle_density, fluid_density, viscosity, diameter, gravity)
    reynolds = np.sqrt(33.7 ** 2 + 0.0408 * ar) - 33.7
    return reynolds * viscosity / (fluid_density * diameter)


def ergun_minimum_fluidization(particle_density, fluid_density, viscosity, diameter, porosity, gravity=9.81):
    """The superficial velocity (m/s) at which Ergun's pressure drop through a bed of voidage
    ``porosity`` carries its buoyant weight, (1 − ε)(ρp − ρf) g per unit length: Wen & Yu's
    balance with the bed's own ε_mf instead of their averaged constants."""
    weight = (1 - porosity) * (particle_density - fluid_density) * gravity
    a = 1.75 * fluid_density * (1 - porosity) / (porosity ** 3 * diameter)
    b = 150.0 * viscosity * (1 - porosity) ** 2 / (porosity ** 3 * diameter ** 2)
    return (-b + np.sqrt(b * b + 4 * a * weight)) / (2 * a)


def richardson_zaki_exponent(terminal_reynolds):
    """n of Richardson & Zaki's U = U_t εⁿ from the terminal Reynolds number Re_t = ρ U_t d/μ:
    Garside & Al-Dibouni (1977, Ind. Eng. Chem. Proc. Des. Dev. 16, 206),
    (5.1 − n)/(n − 2.7) = 0.1 Re_t^0.9, valid for Re_t from 0.001 to 3·10⁴; a column's walls are not
    in it (Richardson & Zaki's own d/D term: ``richardson_zaki_1954_exponent``)."""
    k = 0.1 * np.asarray(terminal_reynolds, float) ** 0.9
    return (5.1 + 2.7 * k) / (1 + k)


def richardson_zaki_1954_exponent(terminal_reynolds, diameter_over_column=0.0):
    """n of Richardson & Zaki (1954, Trans. Inst. Chem. Eng. 32, 35), with their wall term d/D:
    4.65 + 19.5 d/D (Re_t < 0.2), (4.35 + 17.5 d/D) Re_t^−0.03 (< 1), (4.45 + 18 d/D) Re_t^−0.1 (< 200),
    4.45 Re_t^−0.1 (< 500), 2.39 beyond."""
    re, r = float(terminal_reynolds), float(diameter_over_column)
    if re < 0.2:
        return 4.65 + 19.5 * r
    if re < 1:
        return (4.35 + 17.5 * r) * re ** -0.03
    if re < 200:
        return (4.45 + 18 * r) * re ** -0.1
    if re < 500:
        return 4.45 * re ** -0.1
    return 2.39


def richardson_zaki_voidage(superficial_velocity, terminal_speed, exponent):
    """The voidage of a fluidized bed at the superficial velocity U: ε = (U/U_t)^(1/n) (Richardson &
    Zaki 1954), U_t the single particle's terminal speed in unbounded fluid."""
    return (np.asarray(superficial_velocity, float) / terminal_speed) ** (1.0 / exponent)


def beetstra_drag_factor(solid_fraction, reynolds):
    """The drag of a sphere in a random array of equal spheres, Beetstra, van der Hoef & Kuipers
    (2007, AIChE J. 53, 489), fitted to lattice-Boltzmann simulations for solid fractions φ up to 0.6
    and Re up to 1000: F = F_d/(3π μ d U_s), U_s = ε (u − v) the superficial slip, Re = ρ |U_s| d/μ,
    F_d the force less the share of the mean pressure gradient (−V ∇p); the whole force of the fluid
    on a particle in a homogeneous bed is F_d/ε (n F_d/ε = −∇p: the bed's pressure gradient):

        F = 10φ/ε² + ε²(1 + 1.5√φ) + 0.413 Re/(24 ε²) (1/ε + 3φε + 8.4 Re^−0.343)/(1 + 10^(3φ) Re^−(1+4φ)/2).

    At φ → 0 it is Schiller–Naumann-like (1 + 0.0172 Re…); at φ = 0.6 and low Re it lies 21 % above
    Ergun (whose 150 lies below the simulations, as Carman–Kozeny's 180 does not)."""
    phi = np.asarray(solid_fraction, float)
    eps = 1.0 - phi
    re = np.maximum(np.asarray(reynolds, float), 1e-12)
    low = 10 * phi / eps ** 2 + eps ** 2 * (1 + 1.5 * np.sqrt(phi))
    inertial = (0.413 * re / (24 * eps ** 2) * (1 / eps + 3 * phi * eps + 8.4 * re ** -0.343)
                / (1 + 10 ** (3 * phi) * re ** (-(1 + 4 * phi) / 2)))
    return low + inertial


def ergun_drag_factor(solid_fraction, reynolds):
    """Ergun's pressure drop as the force on each sphere of a homogeneous bed, in the form of
    ``beetstra_drag_factor``: F_d/(3π μ d U_s) = ε (150 φ + 1.75 Re)/(18 ε³)."""
    phi = np.asarray(solid_fraction, float)
    eps = 1.0 - phi
    return eps * (150 * phi + 1.75 * np.asarray(reynolds, float)) / (18 * eps ** 3)


def di_felice_drag_factor(solid_fraction, reynolds):
    """The drag of a sphere among spheres, Di Felice (1994, Int. J. Multiphase Flow 20, 153), in the
    form of ``beetstra_drag_factor`` (F_d/(3π μ d U_s), Re = ρ |U_s| d/μ): the drag of a lone sphere
    at the superficial slip, C_D Re/24 with Dallavalle's C_D = (0.63 + 4.8/√Re)², times ε^−χ,

        χ = 3.7 − 0.65 exp(−(1.5 − log₁₀ Re)²/2),

    fitted to fluidization and sedimentation data for Re from 0.01 to 10⁴; it carries Richardson &
    Zaki's expansion (n = χ + 1 at low Re, (χ + 1)/2 at high Re)."""
    re = np.maximum(np.asarray(reynolds, float), 1e-12)
    return (0.63 + 4.8 / np.sqrt(re)) ** 2 * re / 24.0 * di_felice_voidage_function(solid_fraction, re)


def di_felice_voidage_function(solid_fraction, reynolds):
    """Di Felice's factor on a lone sphere's drag at the superficial slip: ε^−χ,
    χ = 3.7 − 0.65 exp(−(1.5 − log₁₀ Re)²/2)."""
    eps = 1.0 - np.asarray(solid_fraction, float)
    chi = 3.7 - 0.65 * np.exp(-0.5 * (1.5 - np.log10(reynolds)) ** 2)
    return eps ** -chi


def di_felice_standard_drag_factor(solid_fraction, reynolds):
    """Di Felice's voidage function on the standard drag curve: ``di_felice_drag_factor`` with the
    lone sphere's C_D from ``standard_drag_coefficient`` (Schiller–Naumann, Clift, Grace & Weber
    from Re 800) instead of Dallavalle's, which lies 7, 11, 13, 20 and 30 % above it at Re 1, 10,
    100, 300 and 1000: C_D Re/24 ε^−χ."""
    re = np.maximum(np.asarray(reynolds, float), 1e-12)
    return standard_drag_coefficient(re) * re / 24.0 * di_felice_voidage_function(solid_fraction, re)
