//! `tagdeflect test start|stop|mark|zero|crack|specimens`: a thin client of a running daemon's
//! control API (SPEC "Tests", docs/methods.md); prints the daemon's JSON answer. `test stop`
//! exits 3 when the daemon says the report could not be made (the folder is complete).

use anyhow::{Context, Result};
use std::path::PathBuf;

/// `tagdeflect test ...`.
#[derive(Debug, clap::Args)]
pub struct TestArgs {
    /// What to do.
    #[command(subcommand)]
    pub action: TestAction,
    /// The daemon's live page.
    #[arg(long, global = true, default_value = "http://127.0.0.1:8080")]
    pub url: String,
    /// The file holding the control token (`[output] http_token_file`, or `<tests>/.token`
    /// written by the daemon at start).
    #[arg(long, global = true, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
}

/// A command of the control API.
#[derive(Debug, clap::Subcommand)]
pub enum TestAction {
    /// Start a test (its zero is taken at its first frame sets).
    Start {
        /// The specimen's id; `next` takes the next untested specimen of the imported table.
        #[arg(long)]
        specimen: String,
        /// The test method (`C1609-19`, `EN14651-05`, or the lab's own; `tagdeflect method list`).
        #[arg(long)]
        method: Option<String>,
        /// Who runs the test.
        #[arg(long)]
        operator: Option<String>,
        /// The standard of the report made at stop (`astm-c1609`, `astm-c1856`, `en-14651`).
        #[arg(long)]
        standard: Option<String>,
        /// Free text.
        #[arg(long)]
        notes: Option<String>,
        /// A measured value, `NAME=NUMBER` (repeatable): `width_mm`, `depth_mm`, `span_mm`,
        /// `notch_mm` replace the config's beam for the report; others are recorded.
        #[arg(long, value_name = "NAME=NUMBER", value_parser = parse_measured)]
        measured: Vec<(String, f64)>,
        /// How many times a start refused because the previous test is still being stopped
        /// (409 with `Retry-After`) is sent again, after the wait the daemon asks for.
        #[arg(long, default_value_t = START_RETRIES, value_name = "N")]
        retries: u32,
    },
    /// Stop the running test; answers once its folder (report included) is complete; exits 3
    /// when the report could not be made.
    Stop {
        /// The crack's position from mid-span, mm (signed), entered with the stop.
        #[arg(long, value_name = "MM", allow_hyphen_values = true)]
        crack_mm: Option<f64>,
    },
    /// Enter where the beam cracked (from mid-span, mm, signed); inside the middle third or not
    /// is computed from the span.
    Crack {
        /// The crack's position from mid-span, mm.
        #[arg(allow_hyphen_values = true)]
        position_mm: f64,
        /// Say inside (`true`) or outside (`false`) the middle third (required when the span is not known).
        #[arg(long)]
        inside_middle_third: Option<bool>,
    },
    /// The specimens entered beforehand.
    Specimens {
        /// Import a table or list it.
        #[command(subcommand)]
        action: SpecimensAction,
    },
    /// Put a note into the feed and the test's record ("first crack seen").
    Mark {
        /// The note.
        note: Option<String>,
    },
    /// Take the test's zero again from the next frame sets.
    Zero,
    /// Print the test's state (no token needed).
    Status,
}

/// `tagdeflect test specimens ...`.
#[derive(Debug, clap::Subcommand)]
pub enum SpecimensAction {
    /// Import a CSV table (`id,width_mm,width_mm,depth_mm,span_mm,cast_date,...`) into the
    /// running daemon's tests folder (`POST /api/specimens`).
    Import {
        /// The CSV file.
        file: PathBuf,
    },
    /// Print the table, each row tested or not (no token needed).
    List,
}

/// `--measured width_mm=150.2`.
fn parse_measured(s: &str) -> Result<(String, f64), String> {
    let (k, v) = s.split_once('=').ok_or_else(|| format!("\"{s}\": NAME=NUMBER, e.g. width_mm=150.2"))?;
    let v: f64 = v.trim().parse().map_err(|_| format!("\"{s}\": {v} is not a number"))?;
    if k.trim().is_empty() || !v.is_finite() {
        return Err(format!("\"{s}\": a name and a finite number"));
    }
    Ok((k.trim().to_string(), v))
}

/// Sends the command and prints the answer; a refusal is an error with the daemon's reason.
pub fn run(args: &TestArgs) -> Result<()> {
    let base = args.url.trim_end_matches('/');
    let agent = ureq::AgentBuilder::new().timeout(std::time::Duration::from_secs(30)).build();
    let (path, body) = match &args.action {
        TestAction::Status => {
            let text = agent.get(&format!("{base}/api/test")).call().map_err(http_error)?.into_string()?;
            println!("{text}");
            return Ok(());
        }
        TestAction::Specimens { action: SpecimensAction::List } => {
            let text = agent.get(&format!("{base}/api/specimens")).call().map_err(http_error)?.into_string()?;
            println!("{text}");
            return Ok(());
        }
        TestAction::Specimens { action: SpecimensAction::Import { file } } => return import(args, &agent, file),
        TestAction::Start { specimen, method, operator, standard, notes, measured, .. } => {
            let measured: serde_json::Map<String, serde_json::Value> = measured.iter().map(|(k, v)| (k.clone(), (*v).into())).collect();
            let body = serde_json::json!({"specimen": specimen, "method": method, "operator": operator, "standard": standard, "notes": notes, "measured": measured});
            ("start", body)
        }
        TestAction::Stop { crack_mm } => ("stop", serde_json::json!({"crack": crack_mm.map(|x| serde_json::json!({"position_mm": x}))})),
        TestAction::Crack { position_mm, inside_middle_third } => {
            ("crack", serde_json::json!({"position_mm": position_mm, "inside_middle_third": inside_middle_third}))
        }
        TestAction::Mark { note } => ("mark", serde_json::json!({"note": note})),
        TestAction::Zero => ("zero", serde_json::json!({})),
    };
    let token = token(args)?;
    // Drop nulls: the API takes absent fields, not nulls.
    let body = match body {
        serde_json::Value::Object(m) => serde_json::Value::Object(m.into_iter().filter(|(_, v)| !v.is_null()).collect()),
        v => v,
    };
    let retries = match &args.action {
        TestAction::Start { retries, .. } => *retries,
        _ => 0,
    };
    // A stop answers once the test's folder is complete: a long test's report and PDF take
    // minutes (a 9-hour test's stop 6 min at load 18, docs/performance.md).
    let agent = match &args.action {
        TestAction::Stop { .. } => ureq::AgentBuilder::new().timeout(STOP_TIMEOUT).build(),
        _ => agent,
    };
    let answer = post_retrying(&agent, &format!("{base}/api/test/{path}"), &token, &body, retries)?;
    println!("{answer}");
    let report_error = serde_json::from_str::<serde_json::Value>(&answer).ok().and_then(|v| v["report_error"].as_str().map(str::to_string));
    if let Some(why) = report_error {
        return Err(tagdeflect_core::NotFit::new(format!("the test stopped and its folder is complete, but {why}")).into());
    }
    Ok(())
}

/// How long `test stop` waits for the daemon's answer (other commands: 30 s).
pub const STOP_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30 * 60);

/// How many times `test start` is sent again by default when the daemon answers that the
/// previous test is still being stopped.
pub const START_RETRIES: u32 = 3;

/// The longest `Retry-After` followed, s (a longer one is waited this long).
const RETRY_AFTER_MAX_S: u64 = 30;

/// Posts `body` to `url`; a 409 with `Retry-After` (a start while the previous test is still
/// being stopped) is sent again after the wait it asks for (at most [`RETRY_AFTER_MAX_S`]),
/// at most `retries` times, each wait said on stderr; then the daemon's refusal as the error.
fn post_retrying(agent: &ureq::Agent, url: &str, token: &str, body: &serde_json::Value, retries: u32) -> Result<String> {
    let mut tries = 0;
    loop {
        match agent.post(url).set("Authorization", &format!("Bearer {token}")).send_json(body.clone()) {
            Ok(r) => return Ok(r.into_string()?),
            Err(ureq::Error::Status(409, r)) if tries < retries && r.header("Retry-After").is_some() => {
                let wait_s = r.header("Retry-After").and_then(|v| v.trim().parse::<u64>().ok()).unwrap_or(5).min(RETRY_AFTER_MAX_S);
                tries += 1;
                let why = refusal(r);
                eprintln!("the daemon refused (409): {why}; sending it again in {wait_s} s (retry {tries} of {retries})");
                std::thread::sleep(std::time::Duration::from_secs(wait_s));
            }
            Err(e) => return Err(http_error(e)),
        }
    }
}

/// The control token from `--token-file`.
fn token(args: &TestArgs) -> Result<String> {
    let token_file = args.token_file.as_ref().ok_or_else(|| {
        tagdeflect_core::BadInput::new(
            "--token-file FILE: the control token (the daemon wrote it to <tests>/.token, or [output] http_token_file)",
        )
    })?;
    let token = std::fs::read_to_string(token_file).with_context(|| format!("cannot read the token file {}", token_file.display()))?;
    Ok(token.lines().next().unwrap_or_default().trim().to_string())
}

/// `test specimens import FILE`: the CSV as it is, to `POST /api/specimens` (the daemon checks
/// every row and names the first bad one by row and column).
fn import(args: &TestArgs, agent: &ureq::Agent, file: &std::path::Path) -> Result<()> {
    let text = std::fs::read_to_string(file).map_err(|e| tagdeflect_core::BadInput::new(format!("{}: {e}", file.display())))?;
    let token = token(args)?;
    let answer = agent
        .post(&format!("{}/api/specimens", args.url.trim_end_matches('/')))
        .set("Authorization", &format!("Bearer {token}"))
        .set("Content-Type", "text/csv")
        .send_string(&text)
        .map_err(|e| http_error(e).context(format!("{}", file.display())))?
        .into_string()?;
    println!("{answer}");
    Ok(())
}

/// The daemon's refusal (its JSON `error`) as bad input, a connection failure as is.
fn http_error(e: ureq::Error) -> anyhow::Error {
    match e {
        ureq::Error::Status(code, resp) => {
            anyhow::Error::new(tagdeflect_core::BadInput::new(format!("the daemon refused ({code}): {}", refusal(resp))))
        }
        other => anyhow::Error::new(tagdeflect_core::RuntimeFailure::new(format!("cannot reach the daemon: {other}"))),
    }
}

/// The daemon's reason in a refusal (its JSON `error`, else the body as is).
fn refusal(resp: ureq::Response) -> String {
    let text = resp.into_string().unwrap_or_default();
    serde_json::from_str::<serde_json::Value>(&text)
        .ok()
        .and_then(|v| v.get("error").and_then(|e| e.as_str()).map(str::to_string))
        .unwrap_or(text)
}
