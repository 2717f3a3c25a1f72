//! The verification in force for each test (`[verification]`, see
//! `tagdeflect_core::verification`): assessed when a test starts and again when it stops, with
//! the camera bumps this daemon has seen, into `test.json` `verification` and the control
//! API's status. The check itself (reading the certificate, hashing the calibration files,
//! the config's geometry) is the binary's, handed in as a [`VerificationCheck`].

use tagdeflect_core::feed::FeedLine;
use tagdeflect_core::verification::InForce;

use super::state::{Inner, LabTests};

/// The verification in force given the bumps seen (camera, when, ns since the Unix epoch);
/// `None` when there is none to name (none configured, or its certificate cannot be read —
/// the check logs why).
pub type VerificationCheck = Box<dyn Fn(&[(String, i64)]) -> Option<InForce> + Send + Sync>;

/// Bumps remembered at most (the oldest dropped first): one is enough to make a verification
/// stale; a few per camera say when.
const MAX_BUMPS: usize = 32;

/// A camera's bump flag stays up for a few lines: a flag within this of the last one noted for
/// that camera is the same bump.
const SAME_BUMP_NS: i64 = 2_000_000_000;

impl LabTests {
    /// Sets the check of the verification in force (once; later calls are ignored).
    pub fn set_verification(&self, check: VerificationCheck) {
        let _ = self.verification.set(check);
    }

    /// The verification in force now, with the bumps seen so far.
    pub(super) fn verification_now(&self, g: &Inner) -> Option<InForce> {
        let v = self.verification.get().and_then(|check| check(&g.bumps))?;
        if !v.stale.is_empty() {
            tracing::warn!("{}", v.describe());
        }
        Some(v)
    }

    /// Notes each camera the line says was bumped (once per bump).
    pub(super) fn note_bumps(g: &mut Inner, line: &FeedLine) {
        for c in line.cameras.iter().filter(|c| c.bumped) {
            let seen = g.bumps.iter().rev().find(|(name, _)| *name == c.name).is_some_and(|(_, t)| line.t_ns - t < SAME_BUMP_NS);
            if !seen {
                g.bumps.push((c.name.clone(), line.t_ns));
                if g.bumps.len() > MAX_BUMPS {
                    g.bumps.remove(0);
                }
            }
        }
    }
}
