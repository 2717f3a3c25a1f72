//! Real tests in the simulator: the load law of the specimen (elastic, or elastic to a first
//! crack then softening or hardening to a residual level, as fibre-reinforced concrete and
//! UHPC behave) and the kinematics of a notched beam in three-point bending (after cracking
//! the two halves turn about the crack tip, so the crack mouth opens).
//!
//! The test is deflection-controlled: the midspan deflection `δ` follows the ramp of
//! [`SimRig::midspan_deflection`](super::SimRig::midspan_deflection) whatever the load does,
//! and the UTM load is the law `P(δ)`:
//!
//! * `elastic`: `P = k δ` (k = `stiffness_kn_per_mm`);
//! * `softening` / `hardening`: `P = k δ` up to the first crack at `δc` =
//!   `crack_deflection_mm` (first-crack load `Pc = k δc`), then a sudden drop to
//!   `(1 − crack_drop) Pc` and an exponential approach to the residual level `r Pc`
//!   (`r` = `residual_ratio`, by default 0.5 softening, 1.5 hardening) over a deflection
//!   scale `softening_mm`: `P = Pc (r + (1 − crack_drop − r) exp(−(δ − δc) / softening_mm))`.
//!
//! Four-point tests keep the elastic curve for the shape of the beam (only the load
//! follows the law). In the notched three-point test the midspan deflection splits into an
//! elastic part `δe`, the elastic curve's share of `P / k` (the elastic curve of a
//! centre-loaded beam, which unloads when the load drops; see the notch's elastic opening
//! below) and a hinge part `δh = δ − δe`: the two halves turn rigidly by `∓φ` about
//! the crack tip at height `crack_tip_mm` above the bottom face (default: notch + 0.6 of the
//! ligament, below the midspan tag at the top), which drops by `δh`; the supports stay on their line (they roll outward), so
//! `δh = (L/2) sin φ + h_tip (1 − cos φ)`. The crack mouth (at the bottom face) opens by
//! about `2 h_tip sin φ`.
//!
//! Before the crack the notch already opens elastically ([`NotchCompliance`]): the mouth
//! opening of a single-edge notched beam in three-point bending by linear elastic fracture
//! mechanics, `CMOD = 6 P S a V1(α) / (E B W²)` with
//! `V1(α) = 0.76 − 2.28 α + 3.87 α² − 2.04 α³ + 0.66 / (1 − α)²`, `α = a / W` (H. Tada,
//! P. C. Paris, G. R. Irwin, *The Stress Analysis of Cracks Handbook*, 3rd ed., ASME 2000,
//! single-edge notched beam in three-point bending, S/W = 4, ±1 % for any α; the relation of
//! Jenq and Shah's two-parameter model, RILEM TC 89-FMT 1990). The elastic deflection `P / k`
//! is split between the elastic curve (Euler–Bernoulli, `P S³ / (4 E B W³)`) and the turn of
//! the halves about the same hinge that opens the mouth after cracking (`δn = S·CMOD / (4 h_tip)`),
//! and `E` is the one for which both add up to the rig's stiffness `k`: the notch's share of
//! the deflection comes from that hinge, not from Tada's own load-point relation (a
//! simplification: the elastic opening is carried by a rigid turn of the halves).

use super::beam::{DeformedBeam, FourPointBeam};
use super::SimParams;
/// The load law and the kind of test are `[sim]` options (`config::sim`).
pub use crate::params::{LoadLaw, SimTest};

/// The residual ratio in force (the option, or the law's default).
pub fn residual_ratio(p: &SimParams) -> f64 {
    p.residual_ratio.unwrap_or(match p.load_law {
        LoadLaw::Hardening => 1.5,
        _ => 0.5,
    })
}

/// The UTM load (kN) at midspan deflection `d` (mm) under the rig's load law.
pub fn load_at(p: &SimParams, d: f64) -> f64 {
    let k = p.stiffness_kn_per_mm;
    if p.load_law == LoadLaw::Elastic || d <= p.crack_deflection_mm {
        return k * d;
    }
    let pc = k * p.crack_deflection_mm;
    let r = residual_ratio(p);
    pc * (r + (1.0 - p.crack_drop - r) * (-(d - p.crack_deflection_mm) / p.softening_mm).exp())
}

/// Height of the crack tip (the hinge of the notched beam) above the bottom face, mm.
pub fn crack_tip_height(p: &SimParams) -> f64 {
    p.crack_tip_height()
}

/// Tada's `V1(α)` of the crack mouth opening of a single-edge notched beam in three-point
/// bending (see the [module docs](self)), `α` = notch depth / beam height.
pub fn tada_v1(alpha: f64) -> f64 {
    0.76 - 2.28 * alpha + 3.87 * alpha.powi(2) - 2.04 * alpha.powi(3) + 0.66 / (1.0 - alpha).powi(2)
}

/// The elastic notched beam (see the [module docs](self)): how its elastic deflection `P / k`
/// splits and how far its mouth opens per mm of it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NotchCompliance {
    /// Share of the elastic deflection in the elastic curve (the rest is the halves' turn).
    pub bend_share: f64,
    /// Elastic crack mouth opening per mm of elastic midspan deflection.
    pub cmod_per_mm: f64,
}

impl NotchCompliance {
    /// The compliance of the rig's notched beam (span `S`, height `W`, notch `a`, hinge at
    /// `h_tip`): with `C = E B δ / P` per part, `C_bend = S³ / (4 W³)`,
    /// `C_cmod = 6 S a V1(a/W) / W²` and the turn's `C_turn = S C_cmod / (4 h_tip)`.
    pub fn of(p: &SimParams) -> NotchCompliance {
        let (s, w, a) = (p.span_mm, p.beam_height_mm, p.notch_mm);
        let bend = s.powi(3) / (4.0 * w.powi(3));
        let cmod = 6.0 * s * a * tada_v1(a / w) / (w * w);
        let turn = s * cmod / (4.0 * crack_tip_height(p));
        NotchCompliance { bend_share: bend / (bend + turn), cmod_per_mm: cmod / (bend + turn) }
    }

    /// Young's modulus of the beam (GPa) for which the notched beam has stiffness `k`.
    pub fn youngs_modulus_gpa(p: &SimParams) -> f64 {
        let (s, w, b) = (p.span_mm, p.beam_height_mm, p.beam_width_mm);
        let bend = s.powi(3) / (4.0 * w.powi(3));
        // k (kN/mm) = E B / (C_bend / share); kN/mm² = GPa.
        p.stiffness_kn_per_mm * bend / (Self::of(p).bend_share * b)
    }
}

/// The rigid turn of the two halves of a cracked notched beam.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hinge {
    /// Turn of each half, rad (left half clockwise, right half counter-clockwise, seen from the front).
    pub phi: f64,
    /// Drop of the crack tip beyond the elastic deflection, mm.
    pub drop: f64,
    /// Height of the crack tip above the neutral axis at rest, mm.
    pub zeta: f64,
    /// Elastic midspan deflection, mm (the tip's elastic drop).
    pub elastic: f64,
}

impl Hinge {
    /// Moves a point `(X, Z)` (already displaced elastically; beam coordinates, `Z` above
    /// the neutral axis at rest) of the half on side `side` (−1 left, +1 right) with the turn.
    #[inline]
    pub fn apply(&self, side: f64, x: f64, z: f64) -> (f64, f64) {
        let (s, c) = (side * self.phi).sin_cos();
        let hz = self.zeta - self.elastic;
        let (rx, rz) = (x, z - hz);
        (c * rx - s * rz, hz - self.drop + s * rx + c * rz)
    }

    /// The inverse of [`apply`](Self::apply).
    #[inline]
    pub fn invert(&self, side: f64, x: f64, z: f64) -> (f64, f64) {
        let (s, c) = (side * self.phi).sin_cos();
        let hz = self.zeta - self.elastic;
        let (rx, rz) = (x, z - hz + self.drop);
        (c * rx + s * rz, hz - s * rx + c * rz)
    }
}

/// The deformation of the beam at one instant: the elastic curve (at the elastic part of
/// the deflection) and, for a cracked notched beam, the hinge.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BeamMotion {
    /// The elastic model (three-point: `load_span = 0`).
    pub beam: FourPointBeam,
    /// Elastic midspan deflection, mm.
    pub elastic: f64,
    /// The halves' turn (notched three-point test after cracking).
    pub hinge: Option<Hinge>,
    /// Notch `(half width, depth)`, mm, for a notched beam.
    pub notch: Option<(f64, f64)>,
    /// Half the beam height, mm.
    pub half_height: f64,
    /// A verification run's rigid motion: the whole beam moved down by this, mm (0 in a test).
    pub rigid_drop_mm: f64,
    /// With a stage (`verify_stage_half_width_mm`): only material within this half width of
    /// midspan moves by `rigid_drop_mm`, the rest holds still; `None`: all of it.
    pub stage_half_width_mm: Option<f64>,
}

impl BeamMotion {
    /// The motion at total midspan deflection `d` for the rig's parameters.
    pub fn new(p: &SimParams, beam: &FourPointBeam, d: f64) -> BeamMotion {
        let hh = 0.5 * p.beam_height_mm;
        if p.test == SimTest::FourPoint {
            return BeamMotion {
                beam: *beam,
                elastic: d,
                hinge: None,
                notch: None,
                half_height: hh,
                rigid_drop_mm: 0.0,
                stage_half_width_mm: None,
            };
        }
        let k = p.stiffness_kn_per_mm;
        let loaded = if p.load_law == LoadLaw::Elastic || k <= 0.0 { d } else { (load_at(p, d) / k).clamp(0.0, d.max(0.0)) };
        // The elastic curve takes its share; the halves' turn the rest (the notch's elastic
        // opening, and after the crack the crack's).
        let elastic = loaded * NotchCompliance::of(p).bend_share;
        let drop = d - elastic;
        let notch = Some((0.5 * p.notch_width_mm, p.notch_mm));
        if drop <= 0.0 {
            return BeamMotion { beam: *beam, elastic, hinge: None, notch, half_height: hh, rigid_drop_mm: 0.0, stage_half_width_mm: None };
        }
        let tip = crack_tip_height(p);
        let half = 0.5 * beam.span;
        let mut phi = (drop / half).min(1.0).asin();
        for _ in 0..6 {
            phi = ((drop - tip * (1.0 - phi.cos())) / half).clamp(-1.0, 1.0).asin();
        }
        BeamMotion {
            beam: *beam,
            elastic,
            hinge: Some(Hinge { phi, drop, zeta: tip - hh, elastic }),
            notch,
            half_height: hh,
            rigid_drop_mm: 0.0,
            stage_half_width_mm: None,
        }
    }

    /// A verification run's motion law: the beam, undeformed and unloaded, moved down as one
    /// by `drop_mm` (a rigid bar on a stage).
    pub fn rigid(p: &SimParams, beam: &FourPointBeam, drop_mm: f64) -> BeamMotion {
        let notch = (p.test == SimTest::ThreePointNotched).then_some((0.5 * p.notch_width_mm, p.notch_mm));
        let stage_half_width_mm = (p.verify_stage_half_width_mm > 0.0).then_some(p.verify_stage_half_width_mm);
        BeamMotion {
            beam: *beam,
            elastic: 0.0,
            hinge: None,
            notch,
            half_height: 0.5 * p.beam_height_mm,
            rigid_drop_mm: drop_mm,
            stage_half_width_mm,
        }
    }

    /// The rigid drop of the material at `x` (mm along the beam from midspan): all of it, or
    /// only the stage's block.
    #[inline]
    fn drop_at(&self, x: f64) -> f64 {
        match self.stage_half_width_mm {
            Some(w) if x.abs() >= w => 0.0,
            _ => self.rigid_drop_mm,
        }
    }

    /// Side of a material point: −1 left of the notch, +1 right (midspan counts right).
    #[inline]
    fn side(x: f64) -> f64 {
        if x < 0.0 {
            -1.0
        } else {
            1.0
        }
    }

    /// `(dx, dz, rotation)` of the material point `(x, zeta)` (see
    /// [`FourPointBeam::displace`]), hinge included.
    pub fn displace(&self, x: f64, zeta: f64) -> (f64, f64, f64) {
        let (dx, dz, rot) = self.beam.displace(x, zeta, self.elastic);
        match &self.hinge {
            None => (dx, dz - self.drop_at(x), rot),
            Some(h) => {
                let side = Self::side(x);
                let (nx, nz) = h.apply(side, x + dx, zeta + dz);
                (nx - x, nz - zeta - self.drop_at(x), rot + side * h.phi)
            }
        }
    }

    /// True when `(x, zeta)` lies in the notch (no material there).
    #[inline]
    pub fn in_notch(&self, x: f64, zeta: f64) -> bool {
        matches!(self.notch, Some((w, depth)) if x.abs() < w && zeta < depth - self.half_height)
    }
}

/// [`DeformedBeam`] with the hinge and the notch of a [`BeamMotion`]: fast lookups for the
/// renderer.
#[derive(Debug, Clone)]
pub struct DeformedShape {
    table: DeformedBeam,
    motion: BeamMotion,
}

impl DeformedShape {
    /// Tabulates the motion's elastic curve over `|x| ≤ half_length`.
    pub fn new(motion: &BeamMotion, half_length: f64) -> Self {
        Self { table: DeformedBeam::new(&motion.beam, motion.elastic, half_length), motion: *motion }
    }

    /// `(dx, dz)` of the material point `(x, zeta)`.
    #[inline]
    pub fn displace(&self, x: f64, zeta: f64) -> (f64, f64) {
        let (dx, dz) = self.table.displace(x, zeta);
        let rigid = self.motion.drop_at(x);
        match &self.motion.hinge {
            None => (dx, dz - rigid),
            Some(h) => {
                let side = BeamMotion::side(x);
                let (nx, nz) = h.apply(side, x + dx, zeta + dz);
                (nx - x, nz - zeta - rigid)
            }
        }
    }

    /// The material point at the deformed face position `(px, pz)`; NaN where there is no
    /// material (the notch, the open crack).
    #[inline]
    pub fn material_point(&self, px: f64, pz: f64) -> (f64, f64) {
        // A rigid motion moves nothing along the beam: the material's x is the face's px.
        let pz = pz + self.motion.drop_at(px);
        let (mx, mz) = match &self.motion.hinge {
            None => self.table.material_point(px, pz),
            Some(h) => {
                let first = BeamMotion::side(px);
                let mut found = (f64::NAN, f64::NAN);
                for side in [first, -first] {
                    let (ex, ez) = h.invert(side, px, pz);
                    let (mx, mz) = self.table.material_point(ex, ez);
                    if BeamMotion::side(mx) == side {
                        found = (mx, mz);
                        break;
                    }
                }
                found
            }
        };
        if self.motion.notch.is_some() && self.motion.in_notch(mx, mz) {
            return (f64::NAN, f64::NAN);
        }
        (mx, mz)
    }

    /// The material `x` of the fibre at height `zeta` whose deformed position is at `px`
    /// along the beam, and that point's vertical displacement `dz`.
    #[inline]
    pub fn fibre_point(&self, px: f64, zeta: f64) -> (f64, f64) {
        if self.motion.hinge.is_none() {
            let (x, dz) = self.table.fibre_point(px, zeta);
            return (x, dz - self.motion.drop_at(x));
        }
        let mut x = px;
        for _ in 0..4 {
            let (dx, _) = self.displace(x, zeta);
            x = px - dx;
        }
        (x, self.displace(x, zeta).1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn notched() -> SimParams {
        SimParams {
            test: SimTest::ThreePointNotched,
            load_law: LoadLaw::Softening,
            span_mm: 500.0,
            stiffness_kn_per_mm: 100.0,
            ..SimParams::default()
        }
    }

    #[test]
    fn softening_and_hardening_laws() {
        let p = SimParams { load_law: LoadLaw::Softening, ..SimParams::default() };
        let (dc, k) = (p.crack_deflection_mm, p.stiffness_kn_per_mm);
        assert!((load_at(&p, 0.5 * dc) - 0.5 * k * dc).abs() < 1e-12);
        assert!((load_at(&p, dc) - k * dc).abs() < 1e-12);
        assert!((load_at(&p, dc + 1e-9) - 0.9 * k * dc).abs() < 1e-6, "the drop at the crack");
        assert!((load_at(&p, 50.0) - 0.5 * k * dc).abs() < 1e-9, "residual level");
        let h = SimParams { load_law: LoadLaw::Hardening, ..p.clone() };
        assert!((load_at(&h, 50.0) - 1.5 * k * dc).abs() < 1e-9);
        let e = SimParams::default();
        assert_eq!(load_at(&e, 3.0), 3.0 * e.stiffness_kn_per_mm);
    }

    /// Tada's V1 at the EN 14651 beam's α = 25/150 = 1/6, by hand:
    /// 0.76 − 0.38 + 0.107 500 − 0.009 444 + 0.950 400 = 1.428 456.
    #[test]
    fn tadas_v1_at_the_en_14651_notch_by_hand() {
        assert!((tada_v1(1.0 / 6.0) - 1.428_456).abs() < 1e-6, "{}", tada_v1(1.0 / 6.0));
        // At α = 0.5: 0.76 − 1.14 + 0.9675 − 0.255 + 2.64 = 2.9725.
        assert!((tada_v1(0.5) - 2.9725).abs() < 1e-12);
    }

    /// The notched beam of 150 × 150 mm, span 450, notch 25, hinge at 100 mm, by hand:
    /// C_bend = 450³/(4·150³) = 6.75, C_cmod = 6·450·25·1.428 456/150² = 4.285 367,
    /// C_turn = 450·4.285 367/(4·100) = 4.821 038; share 6.75/11.571 038 = 0.583 353, CMOD per
    /// mm 4.285 367/11.571 038 = 0.370 353. At 50 kN/mm: E = 50·6.75/(0.583 353·150) =
    /// 3.857 012 GPa, and at the first crack (P = 30 kN, δe = 0.6 mm) Tada's CMOD
    /// 6·30 000·450·25·1.428 456/(3 857.012·150·150²) = 0.222 212 mm = 0.370 353·0.6.
    #[test]
    fn the_elastic_notch_opens_the_mouth_by_tadas_relation_by_hand() {
        let p = SimParams {
            test: SimTest::ThreePointNotched,
            load_law: LoadLaw::Softening,
            stiffness_kn_per_mm: 50.0,
            crack_deflection_mm: 0.6,
            ..SimParams::default()
        };
        let c = NotchCompliance::of(&p);
        assert!((c.bend_share - 0.583_353).abs() < 1e-6 && (c.cmod_per_mm - 0.370_353).abs() < 1e-6, "{c:?}");
        let e_gpa = NotchCompliance::youngs_modulus_gpa(&p);
        assert!((e_gpa - 3.857_012).abs() < 1e-5, "{e_gpa}");
        let tada_mm = 6.0 * 30_000.0 * 450.0 * 25.0 * tada_v1(1.0 / 6.0) / (e_gpa * 1e3 * 150.0 * 150.0 * 150.0);
        assert!((tada_mm - 0.222_212).abs() < 1e-5, "{tada_mm}");
        // The simulated beam's mouth (the notch's edges at the bottom face) before the crack:
        // Tada's opening, growing with the load from the first step, plus the elastic curve's
        // own opening at the edges (±1.5 mm, the bottom fibre 75 mm below the axis):
        // 2·75·12·δb·1.5/450² = 0.007 778 per mm of δ (δb = 0.583 353 δ).
        let rig = crate::SimRig::new(&p).unwrap();
        let per_mm = 0.370_353 + 0.007_778;
        for d in [0.01, 0.1, 0.3, 0.6] {
            let cmod = rig.cmod_at(d).unwrap();
            assert!((cmod - per_mm * d).abs() < 1e-3 * per_mm * d, "CMOD {cmod} mm at {d} mm");
        }
        assert!((rig.cmod_at(0.6).unwrap() - 0.007_778 * 0.6 - tada_mm).abs() < 1e-4);
        // The midspan still deflects by d: the turn and the elastic curve add up.
        let beam = FourPointBeam { span: p.span_mm, load_span: 0.0 };
        let (_, dz, _) = BeamMotion::new(&p, &beam, 0.3).displace(0.0, 0.0);
        assert!((dz + 0.3).abs() < 1e-4, "midspan {dz}");
    }

    #[test]
    fn hinge_keeps_supports_on_their_line_and_opens_the_mouth() {
        let p = notched();
        let beam = FourPointBeam { span: p.span_mm, load_span: 0.0 };
        let m = BeamMotion::new(&p, &beam, 3.0);
        let h = m.hinge.expect("cracked");
        assert!(h.drop > 2.5 && m.elastic < 0.5);
        let hh = 0.5 * p.beam_height_mm;
        // Supports (bottom, x = ±L/2) stay at the support height (to the elastic part's
        // second-order terms), midspan deflects by d.
        for x in [-250.0, 250.0] {
            let (_, dz, _) = m.displace(x, -hh);
            assert!(dz.abs() < 0.01, "support at {x} moved {dz}");
        }
        let (_, dz, _) = m.displace(0.0, 0.0);
        assert!((dz + 3.0).abs() < 0.02, "midspan {dz}");
        // The mouth opens by ≈ 2 h_tip sin φ; the crack tip stays closed.
        let tip = crack_tip_height(&p);
        let (dl, _, _) = m.displace(-1.5, -hh);
        let (dr, _, _) = m.displace(1.5, -hh);
        let cmod = dr - dl;
        assert!((cmod - 2.0 * tip * h.phi.sin()).abs() < 0.02, "cmod {cmod}");
        let (tl, _, _) = m.displace(-1e-9, tip - hh);
        let (tr, _, _) = m.displace(0.0, tip - hh);
        assert!((tr - tl).abs() < 1e-6);
        // The inverse and the notch.
        let shape = DeformedShape::new(&m, 275.0);
        let (dx, dz) = shape.displace(-40.0, -60.0);
        let (mx, mz) = shape.material_point(-40.0 + dx, -60.0 + dz);
        assert!((mx + 40.0).abs() < 1e-3 && (mz + 60.0).abs() < 1e-3, "{mx} {mz}");
        assert!(shape.material_point(0.0, -hh + 5.0).0.is_nan(), "the notch and the crack are empty");
    }
}
