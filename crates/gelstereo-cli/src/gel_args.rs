//! The gel's facts on the command line (`track`, `bench`): each overrides the recording's sensor
//! description (its `meta.json`) and the reference sensor's defaults.

use clap::Args;
use gelstereo::GelFacts;
use gelstereo::PipelineConfig;
use gelstereo::gel::GelFile;

/// `--gel FILE`, `--gel-thickness-mm`, `--gel-modulus-kpa`, `--poisson`, `--friction`.
#[derive(Debug, Clone, Args)]
pub struct GelArgs {
    /// The gel's facts from a file (`gel.json` as `track` or `calibrate-gel` write it); a flag
    /// below that is also given must agree with it.
    #[arg(long, value_name = "FILE")]
    pub gel: Option<std::path::PathBuf>,
    /// Gel thickness between the contact surface and the rigid window, mm. Default: the
    /// recording's sensor description (meta.json), else 2.5 (the reference sensor).
    #[arg(long, value_name = "MM", allow_negative_numbers = true)]
    pub gel_thickness_mm: Option<f64>,
    /// The gel's Young's modulus, kPa: scales pressure and force. Default: the recording's sensor
    /// description, else 150 (the reference sensor).
    #[arg(long, value_name = "KPA", allow_negative_numbers = true)]
    pub gel_modulus_kpa: Option<f64>,
    /// The gel's Poisson ratio, in [0, 0.5). Default: the recording's sensor description, else
    /// 0.45 (the reference sensor).
    #[arg(long, value_name = "RATIO", allow_negative_numbers = true)]
    pub poisson: Option<f64>,
    /// Coulomb friction coefficient between gel and object: a marker slips where its shear
    /// traction reaches it times the pressure. Default: 0.6.
    #[arg(long, value_name = "MU", allow_negative_numbers = true)]
    pub friction: Option<f64>,
}

impl GelArgs {
    /// Writes the given facts into `config` and checks them: a bad value is an error naming the
    /// fact and the range expected. With a sensor description (`sensor`: `config.sensor`, read
    /// from that file) its gel's facts are used, and a flag must agree with them.
    pub fn apply(&self, config: &mut PipelineConfig, sensor: Option<&std::path::Path>) -> anyhow::Result<()> {
        let mut facts = GelFacts {
            thickness_mm: self.gel_thickness_mm,
            modulus_kpa: self.gel_modulus_kpa,
            poisson: self.poisson,
            friction: self.friction,
        };
        if let Some(path) = &self.gel {
            facts = facts.with_file(&GelFile::read(path)?, path)?;
        }
        if let (Some(spec), Some(path)) = (&config.sensor, sensor) {
            facts = facts.with_file(&GelFile::of_sensor(spec), path)?;
        }
        config.apply_gel(&facts).map_err(|e| {
            anyhow::anyhow!(
                "{e} (from --gel, --gel-thickness-mm, --gel-modulus-kpa, --poisson, --friction or the recording's meta.json)"
            )
        })
    }
}
