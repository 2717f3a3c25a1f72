//! Beam mechanics: the closed-form Euler–Bernoulli elastic curve of a simply supported beam
//! in four-point bending, and the displacement of material points of its front face.
//!
//! Beam coordinates: `x` along the beam from midspan (mm), `zeta` height above the neutral
//! axis (mm). Supports at `x = ±span/2`, the two equal loads at `x = ±load_span/2`.
//! `w(x)` is the deflection of the neutral axis, positive downward; plane sections stay
//! plane and normal to the deflected axis, so a section turns by `atan(w'(x))` and a point
//! at height `zeta` moves to `(x + zeta sin a, -w + zeta cos a)` relative to its rest
//! position's neutral-axis point.

/// A beam in four-point bending, scaled so that the midspan deflection is `delta`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FourPointBeam {
    /// Support span, mm.
    pub span: f64,
    /// Distance between the two loads, mm (`span / 3` for loads at the third points).
    pub load_span: f64,
}

impl FourPointBeam {
    /// Shear span `a`: distance from a support to the nearer load.
    pub(crate) fn shear_span(&self) -> f64 {
        0.5 * (self.span - self.load_span)
    }

    /// `EI w(s) / (P/2)` at distance `s` from the left support (`0 ≤ s ≤ span`), the closed form.
    fn shape(&self, s: f64) -> f64 {
        let l = self.span;
        let a = self.shear_span();
        let s = if s > 0.5 * l { l - s } else { s };
        if s <= a {
            s * (3.0 * l * a - 3.0 * a * a - s * s) / 6.0
        } else {
            a * (3.0 * l * s - 3.0 * s * s - a * a) / 6.0
        }
    }

    /// Derivative of [`shape`](Self::shape) with respect to `s`.
    fn shape_slope(&self, s: f64) -> f64 {
        let l = self.span;
        let a = self.shear_span();
        let (s, sign) = if s > 0.5 * l { (l - s, -1.0) } else { (s, 1.0) };
        sign * if s <= a { (l * a - a * a - s * s) / 2.0 } else { a * (l - 2.0 * s) / 2.0 }
    }

    /// Midspan value of `EI w / (P/2)`: `a (3 L² − 4 a²) / 24`.
    fn shape_mid(&self) -> f64 {
        let (l, a) = (self.span, self.shear_span());
        a * (3.0 * l * l - 4.0 * a * a) / 24.0
    }

    /// Deflection (mm, positive downward) at `x` (mm from midspan) for midspan deflection
    /// `delta`. Outside the supports the overhangs stay straight (they carry no moment).
    pub fn deflection(&self, x: f64, delta: f64) -> f64 {
        let h = 0.5 * self.span;
        let k = delta / self.shape_mid();
        if x.abs() <= h {
            k * self.shape(x + h)
        } else {
            // Straight continuation from the support: w = w'(support) * (distance past it).
            let slope_at = if x > 0.0 { self.shape_slope(self.span) } else { self.shape_slope(0.0) };
            let past = x - x.signum() * h;
            k * slope_at * past
        }
    }

    /// Slope `dw/dx` at `x` for midspan deflection `delta`.
    pub(crate) fn slope(&self, x: f64, delta: f64) -> f64 {
        let h = 0.5 * self.span;
        let k = delta / self.shape_mid();
        let xc = x.clamp(-h, h);
        k * self.shape_slope(xc + h)
    }

    /// World-plane displacement of a material point of the face at `(x, zeta)`:
    /// `(dx, dz)` with `dz` positive upward, and the section's rotation angle (rad,
    /// counter-clockwise seen from the front, i.e. `-atan(w')`).
    pub(crate) fn displace(&self, x: f64, zeta: f64, delta: f64) -> (f64, f64, f64) {
        let w = self.deflection(x, delta);
        let a = self.slope(x, delta).atan();
        let (sa, ca) = a.sin_cos();
        (zeta * sa, -w + zeta * (ca - 1.0), -a)
    }

    /// The material point `(x, zeta)` that sits at the deformed face position `(px, pz)`
    /// (`pz` relative to the neutral axis at rest), by fixed-point iteration (the reference
    /// of [`DeformedBeam::material_point`] in the tests).
    #[cfg(test)]
    fn material_point(&self, px: f64, pz: f64, delta: f64) -> (f64, f64) {
        let (mut x, mut zeta) = (px, pz);
        for _ in 0..12 {
            let (dx, dz, _) = self.displace(x, zeta, delta);
            let (nx, nz) = (px - dx, pz - dz);
            let change = (nx - x).abs() + (nz - zeta).abs();
            (x, zeta) = (nx, nz);
            if change < 1e-11 {
                break;
            }
        }
        (x, zeta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn beam() -> FourPointBeam {
        FourPointBeam { span: 450.0, load_span: 150.0 }
    }

    /// Numerical integration of M/EI twice (independent of the closed form) for a unit load.
    fn integrate(b: &FourPointBeam, n: usize) -> Vec<f64> {
        let l = b.span;
        let a = b.shear_span();
        let ds = l / n as f64;
        // Moment for P = 2 (reactions 1): M(s) = s for s < a, a in the middle, l - s after.
        let m = |s: f64| s.min(a).min(l - s);
        let mut theta = vec![0.0; n + 1];
        for i in 1..=n {
            let s0 = (i - 1) as f64 * ds;
            theta[i] = theta[i - 1] + 0.5 * (m(s0) + m(s0 + ds)) * ds;
        }
        let mut w = vec![0.0; n + 1];
        for i in 1..=n {
            w[i] = w[i - 1] + 0.5 * (theta[i - 1] + theta[i]) * ds;
        }
        // Enforce w(0) = w(l) = 0 by removing the linear part (sign: sagging positive).
        let wl = w[n];
        (0..=n).map(|i| -(w[i] - wl * i as f64 / n as f64)).collect()
    }

    #[test]
    fn closed_form_matches_double_integration_of_the_moment() {
        let b = beam();
        let n = 4500;
        let w = integrate(&b, n);
        let k = 6.0 / w[n / 2];
        let mut worst: f64 = 0.0;
        for i in (0..=n).step_by(45) {
            let x = i as f64 * b.span / n as f64 - 0.5 * b.span;
            worst = worst.max((b.deflection(x, 6.0) - k * w[i]).abs());
        }
        println!("closed form vs numerical elastic curve: max difference {worst:.2e} mm");
        assert!(worst < 1e-5, "{worst}");
        assert!((b.deflection(0.0, 6.0) - 6.0).abs() < 1e-12);
        assert!(b.deflection(225.0, 6.0).abs() < 1e-12 && b.deflection(-225.0, 6.0).abs() < 1e-12);
    }

    #[test]
    fn midspan_formula_and_slope() {
        let b = beam();
        // Textbook: δ = P a (3L² − 4a²) / (48 EI); ratio of load-point to midspan deflection.
        let a = b.shear_span();
        let l = b.span;
        let ratio = b.deflection(75.0, 1.0);
        let expect = (a * (3.0 * l * a - 3.0 * a * a - a * a) / 6.0) / (a * (3.0 * l * l - 4.0 * a * a) / 24.0);
        assert!((ratio - expect).abs() < 1e-12);
        for &x in &[-300.0, -200.0, -100.0, -10.0, 50.0, 120.0, 260.0] {
            let fd = (b.deflection(x + 1e-4, 6.0) - b.deflection(x - 1e-4, 6.0)) / 2e-4;
            assert!((fd - b.slope(x, 6.0)).abs() < 1e-7, "slope at {x}: {fd} vs {}", b.slope(x, 6.0));
        }
        assert!(b.slope(0.0, 6.0).abs() < 1e-12);
        assert!(b.slope(-225.0, 6.0) > 0.0, "left of midspan the beam sags toward +x");
    }

    #[test]
    fn table_matches_the_closed_form() {
        let b = beam();
        let t = DeformedBeam::new(&b, 6.0, 275.0);
        let mut worst: f64 = 0.0;
        for i in 0..=1100 {
            let x = -275.0 + i as f64 * 0.5 + 0.123;
            for zeta in [-75.0, 0.0, 75.0] {
                let (dx, dz, _) = b.displace(x, zeta, 6.0);
                let (tx, tz) = t.displace(x, zeta);
                worst = worst.max((dx - tx).abs()).max((dz - tz).abs());
            }
        }
        assert!(worst < 1e-5, "{worst}");
        let (dx, dz, _) = b.displace(100.0, 60.0, 6.0);
        let (mx, mz) = t.material_point(100.0 + dx, 60.0 + dz);
        assert!((mx - 100.0).abs() < 1e-3 && (mz - 60.0).abs() < 1e-3);
        let (fx, fz) = t.fibre_point(100.0 + dx, 60.0);
        assert!((fx - 100.0).abs() < 1e-3 && (fz - dz).abs() < 1e-4);
    }

    #[test]
    fn material_point_inverts_displace() {
        let b = beam();
        for &(x, z) in &[(-225.0, 50.0), (0.0, -50.0), (100.0, 70.0), (270.0, -70.0)] {
            let (dx, dz, _) = b.displace(x, z, 6.0);
            let (mx, mz) = b.material_point(x + dx, z + dz, 6.0);
            assert!((mx - x).abs() < 1e-9 && (mz - z).abs() < 1e-9, "{x},{z} -> {mx},{mz}");
        }
    }
}

/// The deformed beam at one midspan deflection, tabulated along `x` for fast lookups
/// (linear interpolation at 0.25 mm steps: error under 1e-5 mm for lab-scale beams).
#[derive(Debug, Clone)]
pub struct DeformedBeam {
    x0: f64,
    step: f64,
    /// Per grid point: deflection `w`, `sin a`, `cos a` of the section rotation `a = atan w'`.
    table: Vec<(f64, f64, f64)>,
}

impl DeformedBeam {
    /// Tabulates `beam` at midspan deflection `delta` over `|x| ≤ half_length`.
    pub fn new(beam: &FourPointBeam, delta: f64, half_length: f64) -> Self {
        let step = 0.25;
        let x0 = -half_length - 20.0;
        let n = ((2.0 * (half_length + 20.0)) / step).ceil() as usize + 2;
        let table = (0..n)
            .map(|i| {
                let x = x0 + i as f64 * step;
                let (s, c) = beam.slope(x, delta).atan().sin_cos();
                (beam.deflection(x, delta), s, c)
            })
            .collect();
        Self { x0, step, table }
    }

    #[inline]
    fn lookup(&self, x: f64) -> (f64, f64, f64) {
        let f = ((x - self.x0) * (1.0 / self.step)).clamp(0.0, (self.table.len() - 2) as f64);
        let i = f as usize;
        let t = f - i as f64;
        let (a, b) = (self.table[i], self.table[i + 1]);
        (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1), a.2 + t * (b.2 - a.2))
    }

    /// `(dx, dz)` of the material point `(x, zeta)` (see [`FourPointBeam::displace`]).
    #[inline]
    pub fn displace(&self, x: f64, zeta: f64) -> (f64, f64) {
        let (w, s, c) = self.lookup(x);
        (zeta * s, -w + zeta * (c - 1.0))
    }

    /// The material point at the deformed position `(px, pz)` (see
    /// [`FourPointBeam::material_point`]), to 1e-4 mm.
    #[inline]
    pub fn material_point(&self, px: f64, pz: f64) -> (f64, f64) {
        let (mut x, mut zeta) = (px, pz);
        for _ in 0..8 {
            let (dx, dz) = self.displace(x, zeta);
            let (nx, nz) = (px - dx, pz - dz);
            let change = (nx - x).abs() + (nz - zeta).abs();
            (x, zeta) = (nx, nz);
            if change < 1e-4 {
                break;
            }
        }
        (x, zeta)
    }

    /// The material `x` of the fibre at height `zeta` whose deformed position is at `px`
    /// along the beam, and that point's vertical displacement `dz`.
    #[inline]
    pub fn fibre_point(&self, px: f64, zeta: f64) -> (f64, f64) {
        let mut x = px;
        for _ in 0..3 {
            let (dx, _) = self.displace(x, zeta);
            x = px - dx;
        }
        (x, self.displace(x, zeta).1)
    }
}
