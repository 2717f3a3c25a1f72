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

/// Writes the CSV of a feed. The held columns give the load, the deflection and the gauges;
/// the stroke and the tags' displacements are read from the feed again, line by line
/// ([`Feed::for_each_line`]): a feed that changed since it was read is an error.
pub fn write_curve_csv<W: Write>(feed: &Feed, out: W) -> Result<(), ::csv::Error> {
    let mut w = ::csv::Writer::from_writer(out);
    w.write_record(header(feed))?;
    let cols = &feed.columns;
    let ids = feed.tag_ids();
    let t0 = cols.t_ns.first().copied().unwrap_or(0);
    let num = |v: f64| if v.is_nan() { String::new() } else { number(v) };
    let mut failed = None;
    let mut row = Vec::new();
    let read = feed.for_each_line(|k, l| {
        if failed.is_some() {
            return;
        }
        let t_ns = cols.t_ns[k];
        row.clear();
        row.extend([
            t_ns.to_string(),
            format!("{:.6}", (t_ns - t0) as f64 * 1e-9),
            num(cols.load_kn[k]),
            num(l.stroke_mm.unwrap_or(f64::NAN)),
            num(cols.net_deflection_mm[k]),
        ]);
        for g in &cols.gauges {
            row.push(num(g.value[k]));
            row.push(num(if g.value[k].is_nan() { f64::NAN } else { g.sigma[k] }));
        }
        // The line's tags in id order (a repeated id: its last, as a map would keep).
        let mut by_id: Vec<&tagdeflect_core::feed::FeedTag> = l.tags.iter().collect();
        by_id.sort_by_key(|t| t.id);
        for id in &ids {
            let i = by_id.partition_point(|t| t.id <= *id);
            let t = (i > 0 && by_id[i - 1].id == *id).then(|| by_id[i - 1]);
            for c in 0..3 {
                row.push(t.map(|t| number(t.disp_mm[c])).unwrap_or_default());
            }
        }
        if let Err(e) = w.write_record(&row) {
            failed = Some(e);
        }
    });
    if let Some(e) = failed {
        return Err(e);
    }
    read.map_err(|e| ::csv::Error::from(std::io::Error::other(e.to_string())))?;
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
