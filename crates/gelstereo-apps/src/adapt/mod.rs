//! Adapting the localizer to a user's own sensor from an unlabelled recording (`gelstereo adapt`,
//! `docs/localization.md` "Adapting to your sensor").
//!
//! - [`run`] with [`AdaptOptions`]: the whole adaptation. Pseudo-labels from the base models' sure,
//!   lattice-consistent, tracked markers; fine-tuning by `train/gelstereo_train/adapt.py` in the
//!   project's Python environment; the new folder loaded under the model contract and self-tested,
//!   `adapt.json` written, and the folder renamed into place. Everything is written into a temporary
//!   sibling of the output first, so a failed or interrupted run leaves no model folder behind.
//! - [`labels`]: the pseudo-labels alone ([`write_pseudo_labels`] and its parts), the rules that
//!   make a detection a label or an ignore region, and the dataset layout the trainer reads.
//!
//! ```no_run
//! use gelstereo_apps::adapt::{AdaptOptions, run};
//! use gelstereo::LocalizerConfig;
//! let base = LocalizerConfig::default();
//! let options = AdaptOptions::new("my-recording".into(), "data/models-adapted/mine".into(), base);
//! let stop = std::sync::atomic::AtomicBool::new(false);
//! let report = run(&options, &stop, &|_| {})?;
//! println!("{} labels; self-test {} of {}", report.summary.train_labels, report.self_test.found,
//!          report.self_test.drawn);
//! # Ok::<(), gelstereo::Error>(())
//! ```

pub mod labels;
mod output;
mod run;
mod trainer;

pub use labels::{
    GENERATOR, PseudoLabelConfig, PseudoLabelSummary, SkipReason, ViewCandidates, ViewLabels, held_out,
    ignore_mask, label_view, skipped_text, write_pseudo_labels,
};
pub use output::MANIFEST;
pub use run::{AdaptOptions, AdaptReport, Progress, run};
