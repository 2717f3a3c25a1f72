//! `tagdeflect user add|list|remove`: the control API's users (`[output] users_file`,
//! docs/audit.md). A new user's token is made here from the system's random source, printed
//! once and kept nowhere: the file holds its SHA-256. The file is written whole to a temporary
//! file of mode 0600 and renamed over the old one. With `--tests DIR`, the change is appended to
//! that tests folder's audit log (action `user`, by the system user running the command, role
//! `admin`).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use tagdeflect_core::users::{token_sha256, valid_name, Role, User, Users};

/// `tagdeflect user ...`.
#[derive(Debug, clap::Args)]
pub struct UserArgs {
    /// What to do.
    #[command(subcommand)]
    pub action: UserAction,
    /// The users file (`[output] users_file`).
    #[arg(long, global = true, value_name = "FILE")]
    pub users_file: Option<PathBuf>,
    /// Append the change to this tests folder's audit log (`<DIR>/audit.jsonl`).
    #[arg(long, global = true, value_name = "DIR")]
    pub tests: Option<PathBuf>,
}

/// A change to the users file.
#[derive(Debug, clap::Subcommand)]
pub enum UserAction {
    /// Add a user with a fresh token (printed once).
    Add {
        /// Their name (letters, digits, `_`, `-`, `.`, `@`).
        name: String,
        /// `operator`, `reviewer` or `admin`.
        #[arg(long)]
        role: String,
    },
    /// List the users and their roles.
    List,
    /// Remove a user (their token stops working at the daemon's next start).
    Remove {
        /// Their name.
        name: String,
    },
}

/// Runs `tagdeflect user ...`.
pub fn run(args: &UserArgs) -> Result<()> {
    let bad = |m: String| anyhow::Error::new(tagdeflect_core::BadInput::new(m));
    let file = args.users_file.as_ref().ok_or_else(|| bad("--users-file FILE: the users file ([output] users_file)".into()))?;
    let mut users = if file.exists() { Users::read(file).map_err(|e| bad(e.to_string()))? } else { Users::default() };
    match &args.action {
        UserAction::List => {
            crate::graph::lab_test::warn_if_shared(file);
            for u in &users.users {
                println!("{}\t{}", u.name, u.role.as_str());
            }
            Ok(())
        }
        UserAction::Add { name, role } => {
            let role: Role = serde_json::from_value(serde_json::json!(role))
                .map_err(|_| bad(format!("--role {role}: one of operator, reviewer, admin")))?;
            if !valid_name(name) {
                return Err(bad(format!("user \"{name}\": 1 to 64 letters, digits, `_`, `-`, `.`, `@`")));
            }
            if users.users.iter().any(|u| u.name == *name) {
                return Err(bad(format!("user \"{name}\" exists already in {}: remove it first", file.display())));
            }
            let token = fresh_token();
            users.users.push(User { name: name.clone(), role, token_sha256: token_sha256(&token) });
            write_private(file, &users.to_toml()).with_context(|| format!("cannot write {}", file.display()))?;
            log(args.tests.as_deref(), serde_json::json!({"added": name, "role": role.as_str()}))?;
            eprintln!("user {name} ({}) added to {}; their token (shown once, kept nowhere):", role.as_str(), file.display());
            println!("{token}");
            Ok(())
        }
        UserAction::Remove { name } => {
            let before = users.users.len();
            users.users.retain(|u| u.name != *name);
            if users.users.len() == before {
                return Err(bad(format!("no user \"{name}\" in {}", file.display())));
            }
            write_private(file, &users.to_toml()).with_context(|| format!("cannot write {}", file.display()))?;
            log(args.tests.as_deref(), serde_json::json!({"removed": name}))?;
            eprintln!("user {name} removed from {} (a running daemon takes it at its next start)", file.display());
            Ok(())
        }
    }
}

/// 32 random bytes from the system's source, in hex.
fn fresh_token() -> String {
    use rand::RngCore;
    let mut bytes = [0u8; 32];
    rand::rngs::OsRng.fill_bytes(&mut bytes);
    tagdeflect_core::audit::hex(&bytes)
}

/// The change into `<tests>/audit.jsonl`, by the system user, as admin.
fn log(tests: Option<&Path>, detail: serde_json::Value) -> Result<()> {
    let Some(dir) = tests else { return Ok(()) };
    let user = std::env::var("USER").ok().filter(|u| !u.is_empty()).unwrap_or_else(|| "unknown".into());
    let action = tagdeflect_core::audit::AuditAction {
        t_ns: tagdeflect_core::clock::now_epoch_ns(),
        user,
        role: Role::Admin.as_str().into(),
        action: "user".into(),
        test: None,
        detail,
    };
    tagdeflect_core::audit::append(&dir.join("audit.jsonl"), action)?;
    Ok(())
}

/// Writes `text` to `path` through a temporary file of mode 0600, fsync'd and renamed.
fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let tmp = path.with_extension("toml.tmp");
    let mut f = std::fs::OpenOptions::new().create(true).write(true).truncate(true).mode(0o600).open(&tmp)?;
    f.write_all(text.as_bytes())?;
    f.sync_all()?;
    std::fs::rename(&tmp, path)
}
