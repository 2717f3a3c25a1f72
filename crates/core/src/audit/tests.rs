use super::*;

fn action(i: i64) -> AuditAction {
    AuditAction {
        t_ns: 1_000 + i,
        user: "ana".into(),
        role: "operator".into(),
        action: if i == 0 { "start".into() } else { "mark".into() },
        test: Some("B1-20261206".into()),
        detail: serde_json::json!({"note": format!("mark {i}")}),
    }
}

/// A log of `n` entries in a fresh folder; its lines.
fn chain(n: i64) -> (tempfile::TempDir, PathBuf, Vec<String>) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("audit.jsonl");
    let mut log = AuditLog::open(&path).unwrap();
    for i in 0..n {
        log.append(action(i)).unwrap();
    }
    let lines = std::fs::read_to_string(&path).unwrap().lines().map(String::from).collect();
    (dir, path, lines)
}

fn write(path: &Path, lines: &[String]) {
    std::fs::write(path, lines.iter().map(|l| format!("{l}\n")).collect::<String>()).unwrap();
}

#[test]
fn a_chain_of_n_entries_verifies() {
    let (_d, path, lines) = chain(5);
    assert_eq!(lines.len(), 5);
    let s = verify_chain(&path).unwrap();
    assert_eq!(s.entries, 5);
    assert_eq!(s.last_t_ns, Some(1_004));
    let last: AuditEntry = serde_json::from_str(&lines[4]).unwrap();
    assert_eq!(s.last_sha256, last.sha256);
    let first: AuditEntry = serde_json::from_str(&lines[0]).unwrap();
    assert_eq!((first.seq, first.prev_sha256.as_str()), (0, GENESIS_SHA256));
    assert_eq!(last.seq, 4);
    // The hash is of the line without its sha256 key, in the struct's order.
    let without = lines[4].replace(&format!(",\"sha256\":\"{}\"", last.sha256), "");
    assert_eq!(hex(&sha2::Sha256::digest(without.as_bytes())), last.sha256);
    assert!(lines[0].starts_with("{\"seq\":0,\"t_ns\":1000,\"user\":\"ana\",\"role\":\"operator\",\"action\":\"start\""));
}

#[test]
fn a_missing_log_is_an_empty_chain_and_a_reopened_log_continues_it() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("audit.jsonl");
    assert_eq!(verify_chain(&path).unwrap().entries, 0);
    append(&path, action(0)).unwrap();
    append(&path, action(1)).unwrap();
    let mut a = AuditLog::open(&path).unwrap();
    // Another writer appends between two appends of an open log: its line is not forked.
    append(&path, action(2)).unwrap();
    assert_eq!(a.append(action(3)).unwrap().seq, 3);
    assert_eq!(verify_chain(&path).unwrap().entries, 4);
}

#[test]
fn an_edited_field_is_caught_on_its_line() {
    let (_d, path, mut lines) = chain(5);
    lines[2] = lines[2].replace("\"mark 2\"", "\"mark two\"");
    write(&path, &lines);
    let e = verify_chain(&path).unwrap_err();
    assert!(matches!(e, ChainBroken::HashMismatch { line: 3, .. }), "{e}");
    assert!(e.to_string().contains("audit.jsonl:3: sha256"), "{e}");
}

#[test]
fn a_deleted_line_is_caught_where_it_was() {
    let (_d, path, mut lines) = chain(5);
    lines.remove(1);
    write(&path, &lines);
    let e = verify_chain(&path).unwrap_err();
    assert_eq!(e, ChainBroken::SeqGap { path: path.clone(), line: 2, found: 2, expected: 1 });
    // The last line deleted leaves a shorter chain that verifies: the count is the evidence.
    let (_d2, path2, mut lines2) = chain(3);
    lines2.pop();
    write(&path2, &lines2);
    assert_eq!(verify_chain(&path2).unwrap().entries, 2);
}

#[test]
fn a_reordered_pair_is_caught() {
    let (_d, path, mut lines) = chain(5);
    lines.swap(2, 3);
    write(&path, &lines);
    let e = verify_chain(&path).unwrap_err();
    assert_eq!(e.line(), Some(3), "{e}");
    assert!(matches!(e, ChainBroken::SeqGap { found: 3, expected: 2, .. }), "{e}");
}

#[test]
fn a_forged_line_with_its_own_hash_recomputed_but_a_wrong_prev_is_caught() {
    let (_d, path, mut lines) = chain(5);
    let mut forged: AuditEntry = serde_json::from_str(&lines[3]).unwrap();
    forged.user = "mallory".into();
    forged.prev_sha256 = "ab".repeat(32);
    forged.sha256 = forged.expected_sha256();
    lines[3] = serde_json::to_string(&forged).unwrap();
    write(&path, &lines);
    let e = verify_chain(&path).unwrap_err();
    assert!(matches!(e, ChainBroken::PrevLink { line: 4, .. }), "{e}");
    // Forged with the right prev, the next line's link breaks instead.
    let (_d2, path2, mut lines2) = chain(5);
    let mut forged2: AuditEntry = serde_json::from_str(&lines2[3]).unwrap();
    forged2.user = "mallory".into();
    forged2.sha256 = forged2.expected_sha256();
    lines2[3] = serde_json::to_string(&forged2).unwrap();
    write(&path2, &lines2);
    assert!(matches!(verify_chain(&path2).unwrap_err(), ChainBroken::PrevLink { line: 5, .. }));
}

#[test]
fn a_torn_last_line_is_reported_on_open_and_never_extended() {
    let (_d, path, lines) = chain(3);
    let mut text = std::fs::read_to_string(&path).unwrap();
    text.push_str(&lines[2][..40]);
    std::fs::write(&path, &text).unwrap();
    let e = AuditLog::open(&path).unwrap_err();
    assert!(matches!(e, AuditError::Chain(ChainBroken::TornTail { line: 4, .. })), "{e}");
    assert!(e.to_string().contains("audit.jsonl:4: the last line is torn"), "{e}");
    assert!(append(&path, action(9)).is_err());
    assert_eq!(std::fs::read_to_string(&path).unwrap(), text, "nothing appended after a torn line");
    assert!(matches!(verify_chain(&path).unwrap_err(), ChainBroken::TornTail { line: 4, .. }));
}

#[test]
fn a_line_that_is_not_an_entry_is_named() {
    let (_d, path, mut lines) = chain(3);
    lines[1] = "{\"seq\": 1}".into();
    write(&path, &lines);
    let e = verify_chain(&path).unwrap_err();
    assert!(matches!(e, ChainBroken::NotAnEntry { line: 2, .. }), "{e}");
}
