//! The Levenberg–Marquardt of the edge fits: the parametric blurred step ([`super::fit`]) and
//! the learned profile ([`super::profile_fit`]) are both an [`EdgeModel`] — their weighted
//! cost and normal equations at given parameters, how a step is taken and when it is small
//! enough — minimised by the one loop here ([`minimize`]).

use nalgebra::{SMatrix, SVector};

/// An edge model of `N` parameters, fitted by [`minimize`].
pub(super) trait EdgeModel<const N: usize> {
    /// The weighted cost `Σ w r²`, `JᵀWJ` and `JᵀWr` at `x` (`r` = model − pixel value, `J`
    /// its Jacobian in `x`), in one pass over the pixels.
    fn normal_equations(&self, x: &SVector<f64, N>) -> (f64, SMatrix<f64, N, N>, SVector<f64, N>);

    /// The parameters after `step` from `x`, kept in the model's domain.
    fn step_to(&self, x: &SVector<f64, N>, step: &SVector<f64, N>) -> SVector<f64, N> {
        x + step
    }

    /// Whether `step` is so small that the fit has converged: the step is taken without
    /// evaluating the cost (Gauss–Newton converges quadratically here, so what remains after
    /// it is far smaller).
    fn converged(&self, step: &SVector<f64, N>) -> bool;
}

/// Iterations at most.
const MAX_ITERATIONS: usize = 40;
/// The fit gives up when the damping exceeds this.
const MAX_DAMPING: f64 = 1e8;

/// Levenberg–Marquardt from `x` (damping relative to `JᵀWJ`'s diagonal; a step is kept when
/// the cost does not rise): the parameters and their weighted cost.
pub(super) fn minimize<const N: usize, M: EdgeModel<N>>(model: &M, mut x: SVector<f64, N>) -> (SVector<f64, N>, f64) {
    let (mut current, mut jtj, mut jtr) = model.normal_equations(&x);
    let mut lambda = 1e-6;
    for _ in 0..MAX_ITERATIONS {
        let mut damped = jtj;
        for d in 0..N {
            damped[(d, d)] += lambda * jtj[(d, d)].max(1e-9);
        }
        let Some(step) = damped.cholesky().map(|c| c.solve(&(-jtr))) else {
            lambda *= 10.0;
            if lambda > MAX_DAMPING {
                break;
            }
            continue;
        };
        let cand = model.step_to(&x, &step);
        if model.converged(&step) {
            x = cand;
            break;
        }
        let (cost, j2, r2) = model.normal_equations(&cand);
        if cost.is_finite() && cost <= current {
            (x, current, jtj, jtr) = (cand, cost, j2, r2);
            lambda = (lambda * 0.1).max(1e-9);
        } else {
            lambda *= 10.0;
            if lambda > MAX_DAMPING {
                break;
            }
        }
    }
    (x, current)
}

/// Test support: checks `model`'s normal equations at `x` against central differences of
/// its cost, for a model of **one pixel** (weight `w`): then `∇cost = 2 w r J`, so the
/// differences give `J` up to the factor `w r`, and `JᵀWJ = w J Jᵀ`, `JᵀWr = w r J` must
/// follow. `r` is the pixel's residual at `x`.
#[cfg(test)]
pub(super) fn check_one_pixel_jacobian<const N: usize, M: EdgeModel<N>>(model: &M, x: &SVector<f64, N>, w: f64, r: f64, tol: f64) {
    let (cost, jtj, jtr) = model.normal_equations(x);
    assert!((cost - w * r * r).abs() < 1e-9 * (1.0 + cost), "cost {cost} against w r² {}", w * r * r);
    let mut grad = SVector::<f64, N>::zeros();
    for k in 0..N {
        let h = 1e-6 * (1.0 + x[k].abs());
        let (mut lo, mut hi) = (*x, *x);
        lo[k] -= h;
        hi[k] += h;
        grad[k] = (model.normal_equations(&hi).0 - model.normal_equations(&lo).0) / (2.0 * h);
    }
    let j = grad / (2.0 * w * r);
    let scale = 1.0 + j.norm();
    assert!((jtr - w * r * j).norm() < tol * scale * (w * r).abs().max(1.0), "JᵀWr {jtr:?} against {:?}", w * r * j);
    assert!((jtj - w * j * j.transpose()).norm() < tol * scale * scale * w.max(1.0), "JᵀWJ {jtj:?} against {:?}", w * j * j.transpose());
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Vector2};

    /// y = a · exp(b t) on a few points: a small nonlinear model.
    struct Exponential {
        points: Vec<(f64, f64)>,
    }

    impl EdgeModel<2> for Exponential {
        fn normal_equations(&self, x: &Vector2<f64>) -> (f64, Matrix2<f64>, Vector2<f64>) {
            let (mut cost, mut jtj, mut jtr) = (0.0, Matrix2::zeros(), Vector2::zeros());
            for &(t, y) in &self.points {
                let e = (x[1] * t).exp();
                let r = x[0] * e - y;
                let j = Vector2::new(e, x[0] * t * e);
                cost += r * r;
                jtj += j * j.transpose();
                jtr += r * j;
            }
            (cost, jtj, jtr)
        }
        fn converged(&self, step: &Vector2<f64>) -> bool {
            step.norm() < 1e-12
        }
    }

    #[test]
    fn minimizes_a_nonlinear_model_and_its_jacobian_checks() {
        let model = Exponential { points: (0..8).map(|k| k as f64 * 0.25).map(|t| (t, 2.0 * (-0.7 * t).exp())).collect() };
        let (x, cost) = minimize(&model, Vector2::new(1.0, 0.0));
        assert!((x - Vector2::new(2.0, -0.7)).norm() < 1e-8 && cost < 1e-16, "{x:?} cost {cost}");
        let one = Exponential { points: vec![(0.8, 1.3)] };
        let at = Vector2::new(1.1, 0.3);
        let r = at[0] * (at[1] * 0.8f64).exp() - 1.3;
        check_one_pixel_jacobian(&one, &at, 1.0, r, 1e-6);
    }
}
