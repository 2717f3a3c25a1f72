//! The verification in force for each test (`[verification]`, see
//! `tagdeflect_core::verification`): assessed when a test starts and again when it stops, with
//! the camera bumps this daemon has seen, into `test.json` `verification` and the control
//! API's status — there also while no test runs, so the page names it always. The check itself (reading the certificate, hashing the calibration files,
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

/// How long the idle status's verification is kept before it is assessed again (the page asks
/// every second; the check reads the certificate and hashes the calibration files).
const IDLE_CHECK: std::time::Duration = std::time::Duration::from_secs(5);

/// The idle status's verification: when it was assessed, with how many bumps, and what it was.
pub(super) type IdleVerification = std::sync::Mutex<Option<(std::time::Instant, usize, Option<InForce>)>>;

impl LabTests {
    /// Sets the check of the verification in force (once; later calls are ignored).
    pub fn set_verification(&self, check: VerificationCheck) {
        let _ = self.verification.set(check);
    }

    /// The verification in force while no test runs (`GET /api/test`, so the page names it
    /// always): assessed again at most every [`IDLE_CHECK`] or when a camera was bumped, not
    /// under the tests' lock, not logged (the log has it at every start and stop).
    pub(super) fn verification_idle(&self) -> Option<InForce> {
        let check = self.verification.get()?;
        let bumps = self.lock().bumps.clone();
        let mut cache = self.idle_verification.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((at, n, v)) = cache.as_ref() {
            if at.elapsed() < IDLE_CHECK && *n == bumps.len() {
                return v.clone();
            }
        }
        let v = check(&bumps);
        *cache = Some((std::time::Instant::now(), bumps.len(), v.clone()));
        v
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
