//! `tagdeflect assets --out DIR` (hidden; what `scripts/package.sh` runs): the man pages and
//! shell completions, generated from the command line itself so they cannot drift from it.
//!
//! Writes `DIR/man/tagdeflect.1` and one `tagdeflect-COMMAND.1` per command (clap_mangen),
//! and `DIR/completions/tagdeflect.bash`, `_tagdeflect` (zsh) and `tagdeflect.fish`
//! (clap_complete).

use std::path::Path;

use anyhow::{Context, Result};

/// Writes the man pages and completions of `cmd` (the program's whole command line) into `out`.
pub fn write(mut cmd: clap::Command, out: &Path) -> Result<()> {
    let man = out.join("man");
    let comp = out.join("completions");
    for d in [&man, &comp] {
        std::fs::create_dir_all(d).with_context(|| format!("cannot create {}", d.display()))?;
    }
    cmd.build();
    let write_page = |cmd: &clap::Command, name: &str| -> Result<()> {
        let mut buf = Vec::new();
        clap_mangen::Man::new(cmd.clone()).title(name.to_uppercase()).render(&mut buf)?;
        let path = man.join(format!("{name}.1"));
        std::fs::write(&path, buf).with_context(|| format!("cannot write {}", path.display()))
    };
    write_page(&cmd, "tagdeflect")?;
    for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set() && s.get_name() != "help") {
        let name = format!("tagdeflect-{}", sub.get_name());
        let sub = sub.clone().display_name(name.clone()).bin_name(format!("tagdeflect {}", sub.get_name()));
        write_page(&sub, &name)?;
    }
    use clap_complete::{generate_to, Shell};
    for shell in [Shell::Bash, Shell::Zsh, Shell::Fish] {
        generate_to(shell, &mut cmd, "tagdeflect", &comp).with_context(|| format!("cannot write the {shell} completion"))?;
    }
    Ok(())
}
