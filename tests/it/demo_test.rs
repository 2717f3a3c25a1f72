//! `demo --c1609`: the demo is a test — a cracking, softening beam loaded at ASTM C1609's
//! rates in simulated time, played faster than recorded, started and stopped automatically;
//! its report at stop is valid and its strengths are the simulated law's.

use std::path::Path;
use std::process::Command;

use tagdeflect::commands::optional::sim::{DemoTest, RATE_AFTER_L900_MM_PER_MIN, RATE_TO_L900_MM_PER_MIN};
use tagdeflect_sim::load_at;

fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

#[test]
fn the_demo_c1609_test_gives_a_valid_report_with_the_law_s_strengths() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("demo");
    let o = Command::new(env!("CARGO_BIN_EXE_tagdeflect"))
        .args(["demo", "--c1609"])
        .arg(&root)
        .args(["--small", "--speed", "2", "--no-http"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    let tests: Vec<_> = std::fs::read_dir(root.join("tests")).unwrap().flatten().filter(|e| e.path().join("test.json").is_file()).collect();
    assert_eq!(tests.len(), 1, "one test, started and stopped automatically: {err}");
    let folder = tests[0].path();
    let record = read_json(&folder.join("test.json"));
    assert_eq!(record["standard"], "astm-c1609");
    let j = read_json(&folder.join("report").join("report.json"));
    println!("demo --c1609: valid {}, reasons {}, rates {}", j["valid"], j["invalid_reasons"], j["rates"]);
    assert_eq!(j["valid"], true, "{}", j["invalid_reasons"]);

    // The truth: the simulated law's loads at the first peak, L/600 and L/150.
    let params = DemoTest { speed: 2.0, small: true, root: root.clone() }.params();
    let (b, d, l) = (params.beam_width_mm, params.beam_height_mm, params.span_mm);
    let strength = |p_kn: f64| p_kn * 1e3 * l / (b * d * d);
    let truth = [
        ("f1", strength(load_at(&params, params.crack_deflection_mm))),
        ("f600", strength(load_at(&params, l / 600.0))),
        ("f150", strength(load_at(&params, l / 150.0))),
    ];
    for (key, want) in truth {
        let got = j[key]["value"].as_f64().unwrap_or_else(|| panic!("{key}: {}", j[key]));
        let sigma = j[key]["sigma"].as_f64().unwrap_or(0.0);
        println!("{key}: {got:.4} MPa (σ {sigma:.4}), law {want:.4} MPa, error {:+.2} %", 100.0 * (got - want) / want);
        assert!((got - want).abs() <= 0.02 * want, "{key}: {got} MPa against the law's {want} MPa (2 %)");
    }
    // The rates measured are the ones simulated, each inside its window.
    let rates = j["rates"].as_array().unwrap();
    assert_eq!(rates.len(), 2, "{rates:?}");
    for (r, want) in rates.iter().zip([RATE_TO_L900_MM_PER_MIN, RATE_AFTER_L900_MM_PER_MIN]) {
        let got = r["mm_per_min"].as_f64().unwrap();
        assert!((got - want).abs() < 0.1 * want, "{r}: simulated {want} mm/min");
    }
}
