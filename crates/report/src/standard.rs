//! The standards a report follows.

use serde::{Deserialize, Serialize};

/// The standard a report follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Standard {
    /// ASTM C1609/C1609M: fibre-reinforced concrete, third-point loading, net deflection.
    #[serde(rename = "astm-c1609")]
    #[cfg_attr(feature = "clap", value(name = "astm-c1609"))]
    AstmC1609,
    /// ASTM C1856/C1856M (UHPC): the flexural test of C1609 on the specimens C1856 calls
    /// for; the quantities are C1609's, the geometry is taken from the config.
    #[serde(rename = "astm-c1856")]
    #[cfg_attr(feature = "clap", value(name = "astm-c1856"))]
    AstmC1856,
    /// EN 14651: notched beam, three-point loading, CMOD.
    #[serde(rename = "en-14651")]
    #[cfg_attr(feature = "clap", value(name = "en-14651"))]
    En14651,
}

impl Standard {
    /// The name as on the command line and in `report.json`.
    pub fn id(self) -> &'static str {
        match self {
            Standard::AstmC1609 => "astm-c1609",
            Standard::AstmC1856 => "astm-c1856",
            Standard::En14651 => "en-14651",
        }
    }

    /// The standard's title.
    pub fn title(self) -> &'static str {
        match self {
            Standard::AstmC1609 => {
                "ASTM C1609/C1609M — Flexural Performance of Fiber-Reinforced Concrete (Using Beam With Third-Point Loading)"
            }
            Standard::AstmC1856 => {
                "ASTM C1856/C1856M — Fabricating and Testing Specimens of Ultra-High Performance Concrete (flexure per ASTM C1609)"
            }
            Standard::En14651 => {
                "EN 14651 — Test method for metallic fibre concrete: flexural tensile strength (limit of proportionality, residual)"
            }
        }
    }
}
