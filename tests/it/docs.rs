//! The docs that describe the code are checked against it: the crate graph of
//! `docs/architecture.md` against `cargo metadata`, and `docs/configuration.md` against the
//! config schema (every key of every table documented, every documented key known, every
//! documented literal default the value the loader takes when the key is left out).

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use tagdeflect::config::Config;

fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn read(rel: &str) -> String {
    std::fs::read_to_string(repo().join(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"))
}

/// Names in backticks in a markdown table cell.
fn ticked(cell: &str) -> Vec<String> {
    cell.split('`').skip(1).step_by(2).map(str::to_string).collect()
}

#[test]
fn the_architecture_doc_draws_the_crate_graph_cargo_builds() {
    let doc = read("docs/architecture.md");
    let mut drawn: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for line in doc.lines() {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() < 4 || !cells[1].starts_with("`tagdeflect") {
            continue;
        }
        let name = ticked(cells[1]).remove(0);
        drawn.insert(name, ticked(cells[2]).into_iter().collect());
    }
    let out = std::process::Command::new(env!("CARGO"))
        .args(["metadata", "--format-version", "1", "--no-deps", "--offline"])
        .current_dir(repo())
        .output()
        .expect("cargo metadata runs");
    assert!(out.status.success(), "cargo metadata: {}", String::from_utf8_lossy(&out.stderr));
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let packages = meta["packages"].as_array().unwrap();
    let members: BTreeSet<String> = packages.iter().map(|p| p["name"].as_str().unwrap().to_string()).collect();
    let mut built: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for p in packages {
        let deps = p["dependencies"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|d| d["kind"].is_null() && members.contains(d["name"].as_str().unwrap()))
            .map(|d| d["name"].as_str().unwrap().to_string())
            .collect();
        built.insert(p["name"].as_str().unwrap().to_string(), deps);
    }
    assert_eq!(drawn, built, "docs/architecture.md's crate table must be the workspace's dependency graph");
    assert!(built.len() >= 10, "the workspace's crates: {:?}", built.keys());
}

/// A config with every table, from which keys are probed.
fn full_config() -> toml_edit::DocumentMut {
    let mut text = read("config/one-camera.toml");
    text.push_str(
        r#"
[output.mqtt]
url = "mqtt://127.0.0.1:1883"
rig = "frame1"

[output.control]
modbus = "127.0.0.1:5020"

[verification]
certificate = "verify/2026-12-06/verification.json"

[output.analog]
address = "127.0.0.1:5021"
device = "labjack-t"
volts_per_mm = 0.5
range_v = [0.0, 5.0]

[output.auto_test]
start_load_kn = 2.0

[output.feed_rotation]
max_mb = 2000.0

[measure]
quad_decimate = 1.0

[report]
standard = "astm-c1609"
out = "reports"

[report.lab]
specimen = "B1"

[[gauge]]
name = "net"
kind = "net_deflection"

[clock_check]
every_lines = 10

[sim]
cameras = 3
"#,
    );
    text.parse().expect("the probe config is TOML")
}

/// The item at a table path like `camera`, `utm.load` or `background.tag` (first element of an
/// array of tables).
fn table_at<'d>(doc: &'d mut toml_edit::DocumentMut, path: &str) -> &'d mut toml_edit::Table {
    let mut t = doc.as_table_mut();
    for part in path.split('.') {
        let item = t.get_mut(part).unwrap_or_else(|| panic!("the probe config has no [{path}]"));
        t = match item {
            toml_edit::Item::Table(t) => t,
            toml_edit::Item::ArrayOfTables(a) => a.get_mut(0).unwrap(),
            other => panic!("[{path}] is {}", other.type_name()),
        };
    }
    t
}

fn load(doc: &toml_edit::DocumentMut) -> Result<Config, String> {
    Config::from_toml_str(&doc.to_string(), &repo().join("config/probe.toml")).map_err(|e| e.to_string())
}

/// The fields the schema takes in a table: serde names them all when it meets an unknown one.
fn schema_fields(path: &str) -> BTreeSet<String> {
    let mut doc = full_config();
    table_at(&mut doc, path).insert("__probe", toml_edit::value(1));
    let err = load(&doc).expect_err("an unknown key is refused");
    let expected = err.split_once("expected").map(|(_, r)| r).unwrap_or_else(|| panic!("[{path}]: {err}"));
    ticked(expected).into_iter().collect()
}

/// `## [table]` sections of docs/configuration.md: key path → default cell.
fn documented() -> BTreeMap<String, String> {
    let doc = read("docs/configuration.md");
    let mut keys = BTreeMap::new();
    for line in doc.lines() {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() >= 7 && cells[1].starts_with('`') {
            keys.insert(ticked(cells[1]).remove(0), cells[4].to_string());
        }
    }
    keys
}

/// The tables of the config and what the schema calls them.
const TABLES: &[&str] = &[
    "world",
    "sync",
    "camera",
    "background",
    "background.tag",
    "specimen",
    "specimen.tag",
    "specimen.beam",
    "utm",
    "utm.load",
    "utm.stroke",
    "output",
    "output.mqtt",
    "output.control",
    "output.analog",
    "output.auto_test",
    "output.feed_rotation",
    "measure",
    "report",
    "report.lab",
    "gauge",
    "clock_check",
    "verification",
    "sim",
];

/// Keys the schema reads only to refuse them with a better message than "unknown field".
const REFUSED_ON_PURPOSE: &[&str] = &["background.beam"];

#[test]
fn the_configuration_reference_lists_every_key_of_the_schema_and_no_other() {
    let docs = documented();
    // Documented key paths without array markers.
    let doc_keys: BTreeSet<String> = docs.keys().map(|k| k.replace("[]", "")).collect();
    let mut missing = Vec::new();
    for table in TABLES {
        for field in schema_fields(table) {
            let path = format!("{table}.{field}");
            let is_table = TABLES.contains(&path.as_str());
            if !doc_keys.contains(&path) && !is_table && !REFUSED_ON_PURPOSE.contains(&path.as_str()) {
                missing.push(path);
            }
        }
    }
    assert!(missing.is_empty(), "keys of the schema missing from docs/configuration.md: {missing:?}");
    // And every documented key is one the schema takes.
    let mut unknown = Vec::new();
    for key in &doc_keys {
        let (table, field) = key.rsplit_once('.').unwrap_or(("", key));
        if !TABLES.contains(&table) || !schema_fields(table).contains(field) {
            unknown.push(key.clone());
        }
    }
    assert!(unknown.is_empty(), "docs/configuration.md documents keys the schema does not take: {unknown:?}");
    assert!(doc_keys.len() > 120, "{} keys documented", doc_keys.len());
}

#[test]
fn the_documented_defaults_are_the_loaders() {
    let docs = documented();
    let (mut checked, mut literal) = (0, 0);
    let mut wrong = Vec::new();
    for (key, default) in &docs {
        let Some(value) = default.strip_prefix('`').and_then(|d| d.strip_suffix('`')) else { continue };
        literal += 1;
        let plain = key.replace("[]", "");
        let (table, field) = plain.rsplit_once('.').unwrap();
        let Ok(value) = value.parse::<toml_edit::Value>() else {
            wrong.push(format!("{key}: default {value} is not a TOML value"));
            continue;
        };
        let mut without = full_config();
        table_at(&mut without, table).remove(field);
        let mut with = full_config();
        table_at(&mut with, table).insert(field, toml_edit::Item::Value(value.clone()));
        match (load(&without), load(&with)) {
            (Ok(a), Ok(b)) => {
                checked += 1;
                if a != b {
                    wrong.push(format!("{key}: left out is not the same as `{value}`"));
                }
            }
            // A default that makes the probe config invalid (a simulated source beside a
            // v4l2 camera's name, say) cannot be compared here.
            (Err(_), _) | (_, Err(_)) => {}
        }
    }
    assert!(wrong.is_empty(), "{wrong:#?}");
    assert!(checked * 10 >= literal * 8, "only {checked} of {literal} literal defaults could be checked");
}
