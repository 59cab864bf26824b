//! `gelstereo reconstruct`: localization + grid indexing + left/right pairing + triangulation of a
//! stereo recording (or one stereo pair), written as `OUT/markers.csv` (docs/design.md per-frame marker
//! table, displacement and status empty) and one binary PLY point cloud per frame
//! (`OUT/ply/NNNNNN.ply`). The work is [`gelstereo_apps::reconstruct::run`]; this is argument parsing.

use std::path::PathBuf;

use anyhow::bail;
use gelstereo::core::limits;
use gelstereo::markers::Method;
use gelstereo_apps::reconstruct::{Perturbation, ReconstructionJob};

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo reconstruct`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Stereo calibration: OpenCV YAML/XML (K1 D1 K2 D2 R T), or a folder / comma-separated pair of
    /// mrcal .cameramodel files.
    #[arg(long, value_name = "FILE")]
    calib: std::path::PathBuf,
    /// Output folder: markers.csv, ply/NNNNNN.ply, rejected_pairs.csv (markers seen in both views
    /// but not triangulated, with the reason) and, with --evaluate, evaluation.json.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Write into an output folder gelstereo did not write (refused otherwise); only the files
    /// reconstruct writes are replaced.
    #[arg(long)]
    force: bool,
    /// Localization method: blob, marknet or marknet-mre.
    #[arg(long, default_value = "marknet-mre")]
    method: Method,
    /// Use the ground-truth 2-D marker positions of a simulated RECORDING (its markers.csv, markers
    /// visible in each view) instead of a localizer: measures indexing, pairing and triangulation
    /// alone. The positions go through the same indexing as detections do (their ids are not used).
    #[arg(long)]
    from_ground_truth: bool,
    #[command(flatten)]
    perturb: GroundTruthPerturbation,
    /// Seed of the --gt-* perturbations.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Marker lattice ROWSxCOLS (default: the recording's meta.json, else 23x23).
    #[arg(long, value_name = "ROWSxCOLS")]
    grid: Option<String>,
    /// The no-contact reference frame (number in sorted order) that defines the marker ids.
    #[arg(long, default_value_t = 0)]
    reference: usize,
    /// Index every frame against the reference alone, not seeded by the previous frame.
    #[arg(long)]
    no_prior: bool,
    /// Pairs farther than this from their epipolar line are rejected, px.
    #[arg(long, default_value_t = 3.0)]
    max_epipolar_px: f64,
    /// Triangulated points with a larger reprojection error in either view are rejected, px.
    #[arg(long, default_value_t = 2.0)]
    max_reprojection_px: f64,
    /// Do not write the per-frame PLY point clouds.
    #[arg(long)]
    no_ply: bool,
    /// Compare with the ground truth of a simulated RECORDING (markers.csv, frames.csv): 3-D RMSE,
    /// coverage, wrong pairs and grid-index consistency, printed and written to OUT/evaluation.json.
    #[arg(long)]
    evaluate: bool,
    #[command(flatten)]
    localizer: LocalizerArgs,
    /// A stereo recording (folder with left/ and right/), a side-by-side stereo video (left half,
    /// right half), or LEFT RIGHT: two images (one stereo frame) or two folders of images with
    /// matching names.
    #[arg(value_name = "RECORDING | LEFT RIGHT", num_args = 1..=2, required = true)]
    inputs: Vec<PathBuf>,
}

/// Imperfections added to ground-truth positions (with --from-ground-truth), to measure how
/// indexing and pairing hold up under a localizer's noise, misses and false detections.
#[derive(clap::Args, Debug, Clone, Copy)]
struct GroundTruthPerturbation {
    /// Gaussian noise added to each ground-truth coordinate, px (standard deviation, 0 to 1000).
    #[arg(long, default_value_t = 0.0,
          value_parser = |s: &str| limits::parse_number_in(s, 0.0, 1000.0))]
    gt_noise_px: f64,
    /// Fraction of ground-truth markers dropped at random in each view (0 to 1).
    #[arg(long, default_value_t = 0.0,
          value_parser = |s: &str| limits::parse_number_in(s, 0.0, 1.0))]
    gt_missing: f64,
    /// Spurious detections added per view, uniformly over the markers' bounding box (at most 100000).
    #[arg(long, default_value_t = 0,
          value_parser = |s: &str| limits::parse_count_at_most(s, limits::MAX_GT_DUST))]
    gt_dust: usize,
}

impl Args {
    /// The library's job these options describe.
    fn job(&self) -> anyhow::Result<ReconstructionJob> {
        let mut job = ReconstructionJob::new(self.calib.clone(), self.inputs.clone(), self.out.clone());
        job.method = self.method;
        job.force = self.force;
        job.localizer = self.localizer.config()?;
        job.from_ground_truth = self.from_ground_truth.then_some(Perturbation {
            noise_px: self.perturb.gt_noise_px,
            missing: self.perturb.gt_missing,
            dust: self.perturb.gt_dust,
            seed: self.seed,
        });
        job.grid = match &self.grid {
            Some(text) => Some(gelstereo::parse_grid(text, "--grid")?),
            None => None,
        };
        job.reference = self.reference;
        job.use_prior = !self.no_prior;
        job.stereo.max_epipolar_px = self.max_epipolar_px;
        job.triangulation.max_reprojection_error_px = self.max_reprojection_px;
        job.write_ply = !self.no_ply;
        job.evaluate = self.evaluate;
        Ok(job)
    }
}

/// Runs `gelstereo reconstruct`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let summary =
        gelstereo_apps::reconstruct::run(&args.job()?, gelstereo::core::interrupt::flag(), &mut |w| {
            eprintln!("warning: {w}")
        })?;
    if summary.interrupted() {
        bail!(
            "interrupted after {} of {} frames; {} and {} hold those frames",
            summary.processed,
            summary.frames,
            summary.markers_csv.display(),
            summary.rejections_csv.display()
        );
    }
    eprintln!("{}", summary.describe());
    if let Some(evaluation) = &summary.evaluation {
        eprintln!("{}", evaluation.text);
    }
    Ok(())
}
