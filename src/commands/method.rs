//! `tagdeflect method list|show|review`: the test methods a tests folder offers (the shipped
//! ones and the lab's own in `<tests>/methods/`), one method's file as used, and the lab's
//! review of a method file (`<tests>/methods/NAME.review.json`, naming the file's SHA-256; a
//! file changed since voids it), appended to the folder's audit log as a `method` action. See
//! docs/methods.md.

use std::path::PathBuf;

use anyhow::Result;
use tagdeflect_core::method::library::{self, Loaded, MethodError};
use tagdeflect_core::method::MethodReview;

/// `tagdeflect method ...`.
#[derive(Debug, clap::Args)]
pub struct MethodArgs {
    /// What to do.
    #[command(subcommand)]
    pub action: MethodAction,
    /// The tests folder (`[output] tests`): its `methods/` holds the lab's methods and reviews.
    #[arg(long, global = true, default_value = "tests", value_name = "DIR")]
    pub tests: PathBuf,
}

/// A method command.
#[derive(Debug, clap::Subcommand)]
pub enum MethodAction {
    /// List the methods: name, version, standard, where from, reviewed or not.
    List,
    /// Print a method's file as used, with its SHA-256 and review.
    Show {
        /// The method's name (`C1609-19`).
        name: String,
    },
    /// Record the lab's review of a method's file as it is now.
    Review {
        /// The method's name.
        name: String,
        /// Who reviewed it.
        #[arg(long)]
        by: String,
        /// What the review means ("checked against the standard's text; approved for use").
        #[arg(long)]
        meaning: String,
    },
}

/// Runs the command.
pub fn run(args: &MethodArgs) -> Result<()> {
    match &args.action {
        MethodAction::List => {
            for m in library::list(&args.tests) {
                match m {
                    Ok(m) => println!("{}", line(&m)),
                    Err(e) => println!("{}", located(e)),
                }
            }
            Ok(())
        }
        MethodAction::Show { name } => {
            let m = library::find(&args.tests, name).map_err(located)?;
            println!("# {}", line(&m));
            println!("# sha256 {}", m.sha256);
            print!("{}", m.text);
            Ok(())
        }
        MethodAction::Review { name, by, meaning } => {
            let bad = |m: &str| tagdeflect_core::BadInput::new(format!("--{m}: 1 to 200 characters, no control characters"));
            for (k, v) in [("by", by), ("meaning", meaning)] {
                if v.trim().is_empty() || v.len() > 200 || v.chars().any(char::is_control) {
                    return Err(bad(k).into());
                }
            }
            let at = chrono::Utc::now().format("%Y-%m-%dT%H:%M:%SZ").to_string();
            let review = MethodReview { by: by.trim().to_string(), at, meaning: meaning.trim().to_string() };
            let file = library::review(&args.tests, name, review).map_err(located)?;
            // The review is an action of the tests folder's audit log (whoever may write the
            // folder is its admin).
            let action = tagdeflect_core::audit::AuditAction {
                t_ns: tagdeflect_core::clock::now_epoch_ns(),
                user: file.review.by.clone(),
                role: "admin".into(),
                action: "method".into(),
                test: None,
                detail: serde_json::json!({"reviewed": file.name, "version": file.version, "sha256": file.sha256, "meaning": file.review.meaning}),
            };
            let log = args.tests.join("audit.jsonl");
            tagdeflect_core::audit::append(&log, action).map_err(|e| {
                tagdeflect_core::RuntimeFailure::new(format!("{}: the review was written, its audit entry not: {e}", log.display()))
            })?;
            println!("{}", serde_json::to_string_pretty(&file)?);
            Ok(())
        }
    }
}

/// `NAME vVERSION STANDARD EDITION (FROM) reviewed by WHO on WHEN | not reviewed`.
fn line(m: &Loaded) -> String {
    let review = match &m.review {
        Some(r) => format!("reviewed by {} on {}", r.by, r.at),
        None => "not reviewed".to_string(),
    };
    format!("{} v{} {} \"{}\" ({}) {review}", m.method.name, m.method.version, m.method.standard, m.method.edition, m.origin())
}

/// A method's problem located as `FILE:LINE: `key`: message` (bad input, exit 2).
fn located(e: MethodError) -> anyhow::Error {
    match e {
        MethodError::Bad { origin, text, problem } => {
            let line = crate::config::locate::Locator::new(&text).line(&problem.key);
            let at = line.map_or(origin.clone(), |l| format!("{origin}:{l}"));
            tagdeflect_core::BadInput::new(format!("{at}: {problem}")).into()
        }
        MethodError::Io { .. } => tagdeflect_core::RuntimeFailure::new(e.to_string()).into(),
        MethodError::NotFound { .. } => tagdeflect_core::BadInput::new(e.to_string()).into(),
    }
}
