//! Tracking (the default) and full-frame detection give the same answer (issue 42, item 5):
//! the same cameras posed and refused and the same tags solved, set for set, on renders of a
//! camera turned far and on real photos of a camera that moved; no published position is
//! off against the truth or the expected answers.

use crate::common::*;
use crate::tracking::{camera0_state, large_move_params, position_rms, sim_truth};
use tagdeflect_core::feed::FeedLine;

/// Worst distance (mm) of a published tag position from the truth of its set.
fn worst_position_error_mm(lines: &[FeedLine], truth: &[tagdeflect_sim::SimTruthLine]) -> f64 {
    let mut worst: f64 = 0.0;
    for l in lines {
        for t in &l.tags {
            let truth_tag = truth[l.seq as usize].tags.iter().find(|x| x.id == t.id).expect("a simulated tag");
            worst = worst.max((nalgebra::Vector3::from(t.pos_mm) - nalgebra::Vector3::from(truth_tag.center_mm)).norm());
        }
    }
    worst
}

/// Each camera's published state per set: posed, bumped, and the tags solved.
fn state(l: &FeedLine) -> (Vec<(bool, bool)>, Vec<u32>) {
    (l.cameras.iter().map(|c| (c.posed, c.bumped)).collect(), l.tags.iter().map(|t| t.id).collect())
}

/// A camera turned by 20° and moved by 100 mm, for several seeds (renders whose background
/// tags leave and enter the view differently): both modes pose, re-pose and solve the same,
/// set for set, and every published position is within a floor of the truth.
#[test]
fn a_camera_moved_far_is_posed_alike_in_both_modes_and_no_position_is_off() {
    let dir = tempfile::tempdir().unwrap();
    for seed in [61u64, 67, 71] {
        let rec = simulate(dir.path(), &format!("moved-{seed}"), &large_move_params(seed, 6));
        let truth = sim_truth(&rec);
        let (_, tracked, summary) = replay_lines(&rec, false);
        let (_, full, _) = replay_lines(&rec, true);
        let (worst_t, worst_f) = (worst_position_error_mm(&tracked, &truth), worst_position_error_mm(&full, &truth));
        println!(
            "MODES moved far, seed {seed}: posed per set {:?}; worst position error tracking {worst_t:.3} mm, full-frame {worst_f:.3} mm, RMS {:.3} / {:.3} mm; {:?}",
            tracked.iter().map(|l| l.cameras[0].posed).collect::<Vec<_>>(),
            position_rms(&tracked, &truth, 0),
            position_rms(&full, &truth, 0),
            summary.stats
        );
        assert_eq!(tracked.len(), full.len());
        for (a, b) in tracked.iter().zip(&full) {
            assert_eq!(state(a), state(b), "seed {seed}, set {}: tracking publishes what full-frame publishes", a.seq);
            assert_eq!(camera0_state(a), camera0_state(b));
        }
        for l in tracked.iter().chain(&full) {
            assert!(l.cameras[0].posed || l.tags.is_empty(), "seed {seed}, set {}: positions from an unposed camera", l.seq);
        }
        // Measured 2026-12-06: see the test's output; the floor is ~2× the worst seen.
        assert!(worst_t <= 3.0 && worst_f <= 3.0, "seed {seed}: a published position off by {worst_t:.2} / {worst_f:.2} mm");
    }
}
