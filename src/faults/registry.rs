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

static REGISTRY: &[Registration] = &[
    // Readout
    reg!(gain_offset),
    reg!(gaussian_noise),
    Registration { info: &super::glitch::INFO_VERTICAL, create: super::glitch::create_vertical },
    Registration { info: &super::glitch::INFO_HORIZONTAL, create: super::glitch::create_horizontal },
    reg!(smear),
    reg!(lens_flare),
    reg!(channel_shift),
    reg!(dark_current),
    reg!(blooming),
    reg!(row_noise),
    reg!(gamma),
    reg!(jpeg),
    // Physics library (helper physlib)
    reg!(defocus),
    reg!(motion_blur),
    reg!(vignetting),
    reg!(stray_light),
    reg!(prnu),
    reg!(hot_pixels),
    reg!(shot_noise),
    Registration { info: &super::radiation::INFO_COSMIC, create: super::radiation::create_cosmic },
    Registration { info: &super::radiation::INFO_BIT_FLIP, create: super::radiation::create_bit_flip },
    Registration { info: &super::radiation::INFO_DEAD, create: super::radiation::create_dead },
    Registration { info: &super::temporal::INFO_DROP, create: super::temporal::create_drop },
    Registration { info: &super::temporal::INFO_FREEZE, create: super::temporal::create_freeze },
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
    }
}
