//! `curve.csv` (and `tagdeflect export`): one row per feed line, a header with units in
//! brackets: `t_ns`, `time [s]`, `load [kN]`, `stroke [mm]`, `net_deflection [mm]`, per gauge
//! `<name> [unit]` and `<name>_sigma [unit]`, per tag `tag<id>_dx [mm]`, `_dy`, `_dz`.
//! An empty cell is a value the line does not have (never interpolated).

use std::io::Write;

use crate::feed_reader::Feed;

/// The header row.
fn header(feed: &Feed) -> Vec<String> {
    let mut h: Vec<String> =
        ["t_ns", "time [s]", "load [kN]", "stroke [mm]", "net_deflection [mm]"].iter().map(|s| s.to_string()).collect();
    for g in feed.gauge_names() {
        let unit = feed.gauge_unit(&g).unwrap_or_default();
        h.push(format!("{g} [{unit}]"));
        h.push(format!("{g}_sigma [{unit}]"));
    }
    for id in feed.tag_ids() {
        for axis in ["dx", "dy", "dz"] {
            h.push(format!("tag{id}_{axis} [mm]"));
        }
    }
    h
}

/// Writes the CSV of a feed.
pub fn write_curve_csv<W: Write>(feed: &Feed, out: W) -> Result<(), ::csv::Error> {
    let mut w = ::csv::Writer::from_writer(out);
    w.write_record(header(feed))?;
    let gauges = feed.gauge_names();
    let ids = feed.tag_ids();
    let t0 = feed.lines.first().map_or(0, |l| l.t_ns);
    let num = |v: Option<f64>| v.map(number).unwrap_or_default();
    for l in &feed.lines {
        // One map per line: the lookups stay linear in the line's tags.
        let by_id: std::collections::HashMap<u32, &tagdeflect_core::feed::FeedTag> = l.tags.iter().map(|t| (t.id, t)).collect();
        let mut row = vec![
            l.t_ns.to_string(),
            format!("{:.6}", (l.t_ns - t0) as f64 * 1e-9),
            num(l.load_kn),
            num(l.stroke_mm),
            num(l.net_deflection_mm),
        ];
        for g in &gauges {
            let r = l.gauges.get(g);
            row.push(num(r.map(|r| r.value)));
            row.push(num(r.and_then(|r| r.known_sigma())));
        }
        for id in &ids {
            let t = by_id.get(id);
            for k in 0..3 {
                row.push(num(t.map(|t| t.disp_mm[k])));
            }
        }
        w.write_record(&row)?;
    }
    w.flush()?;
    Ok(())
}

/// A number as a spreadsheet should see it: at most 12 significant digits (no binary noise
/// such as `16.860300000000002`), no negative zero.
pub fn number(x: f64) -> String {
    if !x.is_finite() {
        return String::new();
    }
    let r: f64 = format!("{x:.11e}").parse().unwrap_or(x);
    if r == 0.0 {
        return "0".into();
    }
    r.to_string()
}

#[cfg(test)]
mod tests {
    #[test]
    fn numbers_without_binary_noise_or_negative_zero() {
        assert_eq!(super::number(16.860300000000002), "16.8603");
        assert_eq!(super::number(-0.0), "0");
        assert_eq!(super::number(-1e-20), "-0.00000000000000000001");
        assert_eq!(super::number(0.1 + 0.2), "0.3");
        assert_eq!(super::number(1767225600.123456), "1767225600.12");
    }
}
