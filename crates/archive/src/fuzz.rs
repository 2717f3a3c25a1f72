//! The fuzz target of the archive's message checks.

use tagdeflect_wire::TopicLayout;

use crate::db;
use crate::message::check_message;

/// The fuzz target `archive_message` (`fuzz/`, `scripts/fuzz.sh`): arbitrary bytes as a
/// message on a feed, status or acknowledgement topic. The archive's check of a message
/// and the rig's reading of an acknowledgement must return without a panic; what an
/// acknowledgement claims is always inside `0..=high`; runs given the lines of a message
/// keep every seq they were given.
pub fn fuzz_message(data: &[u8]) {
    let layout = TopicLayout::new("tagdeflect/{rig}/{test}").expect("a valid template");
    let (sel, payload) = data.split_first().unwrap_or((&0, &[]));
    let topic = match sel % 5 {
        0 => "tagdeflect/r/t/feed",
        1 => "tagdeflect/r/t/status",
        2 => "tagdeflect/r/t/archive",
        3 => "tagdeflect/r/t/labtest/20261202T101500Z-B12",
        _ => "tagdeflect/r/t/x/feed",
    };
    let _ = check_message(&layout, topic, payload);
    if let Ok(ack) = serde_json::from_slice::<tagdeflect_wire::ArchiveAck>(payload) {
        for r in ack.runs.iter().take(4) {
            if r.high < 1 << 20 && r.gaps.len() <= 64 {
                let held = r.held();
                assert!(held.bounds().is_none_or(|(_, hi)| hi <= r.high));
            }
        }
        let _ = ack.run_of(i64::MIN);
    }
    // Runs from (seq, t_ns) pairs read off the bytes.
    let mut h = db::Holdings::default();
    let mut given = Vec::new();
    for c in payload.chunks_exact(3).take(256) {
        let seq = u64::from(c[0]) % 64;
        let t = i64::from(c[1]) * 256 + i64::from(c[2]);
        let (run, _) = h.assign(seq, t);
        given.push((run, seq));
    }
    for (run, seq) in given {
        assert!(h.run(run).is_some_and(|r| r.held.contains(seq)), "run {run} lost seq {seq}");
    }
}
