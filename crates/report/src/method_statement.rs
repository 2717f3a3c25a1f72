//! The method in force, as the report states it: the test's method and its review by the lab
//! (`test.json` `method`), and the rules the report applies, each with the public source it
//! implements (the clause of ASTM C1609-19, EN 14651:2005+A1:2007 or ASTM C1856-17 as the
//! documents' published tables of contents and summaries number them).

use crate::standard::Standard;
use tagdeflect_core::method::MethodRef;

/// One rule the report applies and where it comes from.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RuleSource {
    /// What the report does by it.
    pub rule: &'static str,
    /// The document and clause it implements.
    pub source: &'static str,
}

const fn r(rule: &'static str, source: &'static str) -> RuleSource {
    RuleSource { rule, source }
}

/// ASTM C1609/C1609M-19a, Flexural Performance of Fiber-Reinforced Concrete (Using Beam With
/// Third-Point Loading), <https://www.astm.org/c1609_c1609m-19a.html>.
const C1609: [RuleSource; 8] = [
    r("third-point loading of an unnotched beam; net deflection at mid-span relative to the supports", "ASTM C1609-19 §4 Summary of Test Method, §6 Apparatus (Fig. 1)"),
    r("first-peak load P1 (first point of zero slope), peak load Pp, residual loads P600 and P150 at L/600 and L/150", "ASTM C1609-19 §3 Terminology"),
    r("strengths f = P·L/(b·d²) of P1, Pp, P600, P150", "ASTM C1609-19 §9 Calculation, Eq. 1"),
    r("toughness T150: area under the curve to L/150; R_T,150 = 150·T150/(f1·b·d²)", "ASTM C1609-19 §3 Terminology, §9 Calculation, Eq. 2"),
    r("rate of net deflection: 0.025–0.075 mm/min (d ≤ 125 mm) or 0.035–0.10 mm/min (larger) up to L/900, then up to 0.05–0.20 / 0.05–0.30 mm/min", "ASTM C1609-19 §8 Procedure, Table 1"),
    r("the test carried to a net deflection of L/150", "ASTM C1609-19 §8 Procedure"),
    r("a fracture outside the middle third of the span invalidates the test (the operator's crack entry)", "ASTM C1609-19 §9 (by ASTM C78's rule)"),
    r("dimensions measured per specimen (width, depth, span)", "ASTM C1609-19 §8 Procedure; §10 Report"),
];

/// EN 14651:2005+A1:2007, Test method for metallic fibred concrete — Measuring the flexural
/// tensile strength (limit of proportionality (LOP), residual).
const EN14651: [RuleSource; 6] = [
    r(
        "three-point loading of a beam notched at mid-span; the CMOD across the notch",
        "EN 14651:2005+A1:2007 §5 Principle, §6 Apparatus, §7 Test specimens",
    ),
    r("F_L: the largest load up to CMOD 0.05 mm; f_L = 3·F_L·l/(2·b·h_sp²)", "EN 14651:2005+A1:2007 §9.1, Eq. 1"),
    r("F_R,j at CMOD 0.5, 1.5, 2.5, 3.5 mm; f_R,j = 3·F_R,j·l/(2·b·h_sp²)", "EN 14651:2005+A1:2007 §9.2, Eq. 2"),
    r("rate of CMOD: 0.05 mm/min up to CMOD 0.1 mm, then 0.2 mm/min", "EN 14651:2005+A1:2007 §8 Procedure"),
    r("the test carried to a CMOD of at least 3.5 mm", "EN 14651:2005+A1:2007 §8 Procedure"),
    r(
        "the crack entry is not a validity rule (the notch fixes where the beam cracks)",
        "EN 14651:2005+A1:2007 §7 Test specimens (notching)",
    ),
];

/// ASTM C1856/C1856M-17, Fabricating and Testing Specimens of Ultra-High Performance Concrete.
const C1856: [RuleSource; 2] = [
    r(
        "flexural performance of UHPC prisms tested by ASTM C1609 (its rules below)",
        "ASTM C1856-17 §1.1 Scope and its flexural-test clause, which refers to ASTM C1609",
    ),
    r(
        "deflection-hardening response accepted when stated (first peak may lie beyond L/150)",
        "ASTM C1856-17 (UHPC) with ASTM C1609-19 §3 Terminology",
    ),
];

/// Every rule the report applies for `standard`, with its public source.
pub fn rules(standard: Standard) -> Vec<RuleSource> {
    match standard {
        Standard::AstmC1609 => C1609.to_vec(),
        Standard::AstmC1856 => C1856.iter().chain(C1609.iter()).cloned().collect(),
        Standard::En14651 => EN14651.to_vec(),
    }
}

/// What a method file's rule key means, as the report's rule column says it.
fn rule_meaning(rule: &str) -> &'static str {
    match rule {
        "requires" => "the dimensions the report needs (measured per specimen)",
        "preload_kn" => "the preload at which the zero is taken",
        "max_start_load_kn" => "no start (and no zero) above this load",
        "phase" => "the rate of each phase of loading, checked over the phase",
        "end" => "the end criterion the test is carried to",
        "results" => "the results reported and how they are computed",
        "validity" => "what makes a test invalid",
        _ => "a rule of the method",
    }
}

/// The rules in force with their sources, `(rule, source)`: the method file's own
/// `[[source]]` rows when the test ran under a method (the file of its hash), else the
/// built-in rules of `standard` ([`rules`]).
pub fn rules_in_force(method: Option<&tagdeflect_core::method::Method>, standard: Standard) -> Vec<(String, String)> {
    match method {
        Some(m) => m
            .sources
            .iter()
            .map(|s| {
                let url = s.url.as_deref().map_or(String::new(), |u| format!(" ({u})"));
                (format!("{}: {}", s.rule, rule_meaning(&s.rule)), format!("{}, {}{url}", s.document, s.clause))
            })
            .collect(),
        None => rules(standard).into_iter().map(|r| (r.rule.to_string(), r.source.to_string())).collect(),
    }
}

/// The sentence the report carries about the method in force: the test's method and the
/// lab's review of it, its lack of review, or the built-in rules.
pub fn statement(method: Option<&MethodRef>, standard: Standard) -> String {
    match method {
        Some(m) => match &m.review {
            Some(rv) => {
                let day = rv.at.get(..10).unwrap_or(&rv.at);
                let meaning = if rv.meaning.trim().is_empty() { String::new() } else { format!(" ({})", rv.meaning.trim()) };
                format!("Method {}, reviewed by {} on {day}{meaning}.", m.label(), rv.by)
            }
            None => format!("Method {}, not reviewed by the lab.", m.label()),
        },
        None => format!(
            "No test method was named: the built-in rules of {} apply, each listed with the clause it implements under Method.",
            standard.title()
        ),
    }
}
