//! `gelstereo doctor`: one line per component a user needs, with a one-line fix for each problem.
//! The checks are [`gelstereo_apps::doctor::checks`].

use std::path::PathBuf;

use anyhow::bail;
use gelstereo_apps::doctor::Need;

use crate::project;

/// Arguments of `gelstereo doctor`.
#[derive(clap::Args)]
pub struct Args {
    /// Folder with the models to check (default: the shipped models: data/models of the project, or
    /// the copy compiled into this binary).
    #[arg(long)]
    models: Option<PathBuf>,
}

/// Runs `gelstereo doctor`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let home = project::home();
    let models = args
        .models
        .clone()
        .unwrap_or_else(gelstereo::models::shipped_models);
    let mut missing_required = 0;
    for c in &gelstereo_apps::doctor::checks(&home, &models) {
        match &c.outcome {
            Ok(what) => println!("ok       {:<20} {what}", c.name),
            Err(why) => {
                let tag = if c.need == Need::Required {
                    "MISSING"
                } else {
                    "warning"
                };
                missing_required += usize::from(c.need == Need::Required);
                println!(
                    "{tag:<8} {:<20} {why}\n         {:<20} fix: {}",
                    c.name, "", c.fix
                );
            }
        }
    }
    if missing_required > 0 {
        bail!("{missing_required} required component(s) missing, see above");
    }
    println!("all required components present");
    Ok(())
}
