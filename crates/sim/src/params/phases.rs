//! The schedules written as text in `[sim]`: the rate phases of a test (`rates`), the positions
//! of a verification run (`verify_steps`), and the notched beam's hinge height.

use tagdeflect_core::Problem;

use super::SimParams;

impl SimParams {
    /// The phases of a test loaded at rates (`rates`): `(mm/min, until mm)`, the last until
    /// `max_deflection_mm`; empty for the ramp.
    pub fn rate_phases(&self) -> Result<Vec<(f64, f64)>, Problem> {
        let text = self.rates.trim();
        if text.is_empty() {
            return Ok(Vec::new());
        }
        let bad = |v: &str| Problem::new("rates", format!("{v:?}: expected RATE[:UNTIL_MM],… in mm/min and mm, positive, rising"));
        let mut phases = Vec::new();
        let mut last_until = 0.0;
        let parts: Vec<&str> = text.split(',').collect();
        for (k, part) in parts.iter().enumerate() {
            let mut it = part.split(':').map(|v| v.trim().parse::<f64>().ok().filter(|x| x.is_finite() && *x > 0.0));
            let rate = it.next().flatten().ok_or_else(|| bad(part))?;
            let until = match it.next() {
                Some(u) => u.ok_or_else(|| bad(part))?,
                None if k + 1 == parts.len() => self.max_deflection_mm,
                None => return Err(bad(part)),
            };
            if it.next().is_some() || until <= last_until {
                return Err(bad(part));
            }
            last_until = until;
            phases.push((rate, until.min(self.max_deflection_mm)));
        }
        Ok(phases)
    }

    /// The positions of a verification run (`verify_steps`), mm downward; empty for a test.
    pub fn verify_positions_mm(&self) -> Result<Vec<f64>, Problem> {
        let text = self.verify_steps.trim();
        if text.is_empty() {
            return Ok(Vec::new());
        }
        text.split(',')
            .map(|v| {
                v.trim().parse::<f64>().ok().filter(|p| p.is_finite()).ok_or_else(|| {
                    Problem::new("verify_steps", format!("{v:?} is not a number: expected positions in mm, comma-separated"))
                })
            })
            .collect()
    }

    /// Height of the crack tip (the hinge of the notched beam) above the bottom face, mm.
    pub(crate) fn crack_tip_height(&self) -> f64 {
        self.crack_tip_mm.unwrap_or(self.notch_mm + 0.6 * (self.beam_height_mm - self.notch_mm))
    }
}
