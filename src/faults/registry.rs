//! Every effect faultcam knows, by name. Add one line per effect.

use super::{Effect, EffectInfo};

/// One registered effect.
pub struct Registration {
    pub info: &'static EffectInfo,
    pub create: fn() -> Box<dyn Effect>,
}

macro_rules! reg {
    ($m:ident) => {
        Registration { info: &super::$m::INFO, create: super::$m::create }
    };
}

/// In physical order (stage, then order within the stage), as `faultcam effects` lists them.
static REGISTRY: &[Registration] = &[
    // Optics
    reg!(lens_flare),
    reg!(veiling_glare),
    reg!(stray_light),
    reg!(vignetting),
    reg!(defocus),
    reg!(motion_blur),
    reg!(channel_shift),
    // Sensor
    reg!(prnu),
    reg!(shot_noise),
    reg!(dark_current),
    reg!(hot_pixels),
    Registration { info: &super::radiation::INFO_COSMIC, create: super::radiation::create_cosmic },
    reg!(blooming),
    reg!(smear),
    Registration { info: &super::radiation::INFO_DEAD, create: super::radiation::create_dead },
    // Readout
    reg!(gaussian_noise),
    reg!(row_noise),
    Registration { info: &super::glitch::INFO_VERTICAL, create: super::glitch::create_vertical },
    Registration { info: &super::glitch::INFO_HORIZONTAL, create: super::glitch::create_horizontal },
    reg!(gain_offset),
    reg!(gamma),
    // Transmission
    reg!(jpeg),
    Registration { info: &super::radiation::INFO_BIT_FLIP, create: super::radiation::create_bit_flip },
    Registration { info: &super::temporal::INFO_FREEZE, create: super::temporal::create_freeze },
    Registration { info: &super::temporal::INFO_DROP, create: super::temporal::create_drop },
    Registration { info: &super::temporal::INFO_DELAY, create: super::temporal::create_delay },
    Registration { info: &super::temporal::INFO_JITTER, create: super::temporal::create_jitter },
    Registration { info: &super::temporal::INFO_REORDER, create: super::temporal::create_reorder },
];

/// All effects, in registration order.
pub fn all() -> &'static [Registration] {
    REGISTRY
}

/// Effect by name.
pub fn find(name: &str) -> Option<&'static Registration> {
    REGISTRY.iter().find(|r| r.info.name == name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_and_specs_are_sane() {
        for (i, r) in all().iter().enumerate() {
            assert!(all()[..i].iter().all(|o| o.info.name != r.info.name), "duplicate {}", r.info.name);
            assert_eq!((r.create)().info().name, r.info.name);
            assert!(r.info.params.len() <= super::super::MAX_PARAMS);
            for p in r.info.params {
                assert!(p.min <= p.default && p.default <= p.max, "{}.{} default out of range", r.info.name, p.name);
                assert!(!p.doc.is_empty() && !p.unit.is_empty());
            }
            assert!(!r.info.model.is_empty());
        }
        let keys: Vec<_> = all().iter().map(|r| (r.info.stage, r.info.order)).collect();
        assert!(keys.windows(2).all(|w| w[0] < w[1]), "registry in physical order, orders unique per stage");
    }

    /// The effect vocabulary of EFFECTS.md (shared): every name with exactly its canonical
    /// parameters (the ones `diagnose` fits and configs use with these meanings).
    const VOCABULARY: &[(&str, &[&str])] = &[
        ("defocus", &["sigma_px"]),
        ("motion_blur", &["length_px", "angle_deg"]),
        ("vignetting", &["strength"]),
        ("stray_light", &["amplitude_dn"]),
        ("veiling_glare", &["fraction"]),
        ("lens_flare", &["ghosts", "intensity"]),
        ("channel_shift", &["dx_r", "dy_r", "dx_b", "dy_b"]),
        ("prnu", &["sigma"]),
        ("blooming", &["full_well_fraction", "spread_px"]),
        ("smear", &["strength", "direction"]),
        ("dark_current", &["mean_dn", "hot_pixel_rate"]),
        ("hot_pixels", &["rate"]),
        ("shot_noise", &["gain_e_per_dn"]),
        ("gaussian_noise", &["sigma_dn"]),
        ("row_noise", &["sigma_dn"]),
        ("vertical_glitch", &["count", "max_offset_px"]),
        ("horizontal_glitch", &["count", "max_offset_px"]),
        ("gain_offset", &["gain", "offset_dn"]),
        ("gamma", &["gamma"]),
        ("jpeg", &["quality"]),
        ("frame_drop", &["p"]),
        ("frame_freeze", &["frames"]),
        ("frame_delay", &["ms"]),
        ("jitter", &["ms"]),
        ("reorder", &["depth"]),
        ("cosmic_rays", &["rate", "track_len_px"]),
        ("bit_flip", &["rate"]),
        ("dead_pixels", &["rate"]),
    ];

    #[test]
    fn every_effect_of_the_vocabulary_is_registered_with_its_canonical_parameters() {
        assert_eq!(all().len(), VOCABULARY.len(), "registered effects that EFFECTS.md does not list");
        for (name, canonical) in VOCABULARY {
            let r = find(name).unwrap_or_else(|| panic!("{name} (EFFECTS.md) is not registered"));
            let got: Vec<_> = r.info.params.iter().filter(|p| p.canonical).map(|p| p.name).collect();
            assert_eq!(&got, canonical, "{name}: canonical parameters");
            // A fitter searches log-scaled parameters by their logarithm: their range must be
            // positive, or start at 0 (the identity) with a positive upper end.
            for p in r.info.params.iter().filter(|p| p.scale == super::super::Scale::Log) {
                assert!(p.min >= 0.0 && p.max > 0.0, "{name}.{}", p.name);
            }
        }
    }
}
