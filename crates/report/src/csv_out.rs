//! `curve.csv` (and `tagdeflect export`): one row per feed line, a header with units in
//! brackets: `t_ns`, `time [s]`, `load [kN]`, `stroke [mm]`, `net_deflection [mm]`, per gauge
//! `<name> [unit]` and `<name>_sigma [unit]`, per tag `tag<id>_dx [mm]`, `_dy`, `_dz`.
//! An empty cell is a value the line does not have (never interpolated).

use std::io::Write;

use super::Feed;

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
    let num = |v: Option<f64>| v.map(|x| x.to_string()).unwrap_or_default();
    for l in &feed.lines {
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
            let t = l.tags.iter().find(|t| t.id == *id);
            for k in 0..3 {
                row.push(num(t.map(|t| t.disp_mm[k])));
            }
        }
        w.write_record(&row)?;
    }
    w.flush()?;
    Ok(())
}
