//! `--pad-border` of `detect` and `track`, kept for the scripts that pass it: the localizer finds the
//! markers cut by the image border and places them at their centre by itself
//! (docs/localization.md, "Borders"), so a number given is accepted and ignored, with a note.

/// `auto` (the default: the localizer's own border handling) or a number of pixels (ignored).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PadBorder {
    #[default]
    Auto,
    Px(u16),
}

/// Largest number of pixels accepted, as before.
const MAX_PX: u16 = 256;

impl std::str::FromStr for PadBorder {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(Self::Auto);
        }
        match s.parse::<u16>() {
            Ok(px) if px <= MAX_PX => Ok(Self::Px(px)),
            _ => Err(format!(
                "expected `auto` or a number of pixels in 0..={MAX_PX}, found `{s}`"
            )),
        }
    }
}

impl std::fmt::Display for PadBorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Auto => f.write_str("auto"),
            Self::Px(px) => write!(f, "{px}"),
        }
    }
}

impl PadBorder {
    /// Says on standard error that a number given is no longer needed.
    pub fn note_if_given(self) {
        if let Self::Px(px) = self {
            eprintln!(
                "note: --pad-border {px} is ignored: markers cut by the image border are found and placed at \
                 their centre by default, and none whose centre lies outside the image is reported"
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_and_numbers_up_to_256_parse() {
        assert_eq!("auto".parse::<PadBorder>(), Ok(PadBorder::Auto));
        assert_eq!("8".parse::<PadBorder>(), Ok(PadBorder::Px(8)));
        let err = "1000".parse::<PadBorder>().unwrap_err();
        assert!(err.contains("0..=256") && err.contains("1000"), "{err}");
        assert!("-1".parse::<PadBorder>().is_err());
    }
}
