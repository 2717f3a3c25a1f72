//! The synthetic rig: scene, beam mechanics, renderer and ground truth.

use serde::{Deserialize, Serialize};

/// Parameters of the simulated rig (`[sim]` in a config; the options of `simulate`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimParams {
    /// Seed of every random choice.
    pub seed: u64,
}

impl Default for SimParams {
    fn default() -> Self {
        Self { seed: 1 }
    }
}
