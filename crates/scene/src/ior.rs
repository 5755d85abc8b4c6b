//! Named indices of refraction (dielectrics) and complex IORs (conductors).

use glam::Vec3;

/// Mitsuba 3's named dielectric IORs (`include/mitsuba/render/ior.h`; values
/// from Hecht, Optics, measured at ~589 nm). Lookup is case-insensitive.
const IOR_TABLE: &[(&str, f32)] = &[
    ("vacuum", 1.0),
    ("helium", 1.000036),
    ("hydrogen", 1.000132),
    ("air", 1.000277),
    ("carbon dioxide", 1.00045),
    ("water", 1.3330),
    ("acetone", 1.36),
    ("ethanol", 1.361),
    ("carbon tetrachloride", 1.461),
    ("glycerol", 1.4729),
    ("benzene", 1.501),
    ("silicone oil", 1.52045),
    ("bromine", 1.661),
    ("water ice", 1.31),
    ("fused quartz", 1.458),
    ("pyrex", 1.470),
    ("acrylic glass", 1.49),
    ("polypropylene", 1.49),
    ("bk7", 1.5046),
    ("sodium chloride", 1.544),
    ("amber", 1.55),
    ("pet", 1.5750),
    ("diamond", 2.419),
];

/// Look up a named IOR (case-insensitive); on failure the error lists the choices.
pub(crate) fn lookup_ior(name: &str) -> Result<f32, String> {
    let lower = name.to_ascii_lowercase();
    IOR_TABLE
        .iter()
        .find(|(n, _)| *n == lower)
        .map(|(_, v)| *v)
        .ok_or_else(|| {
            let names: Vec<&str> = IOR_TABLE.iter().map(|(n, _)| *n).collect();
            format!(
                "unknown IOR name \"{name}\"; valid choices are: {}",
                names.join(", ")
            )
        })
}

/// Named conductors: RGB `(eta, k)` exactly as Mitsuba 3's `scalar_rgb`
/// variant uses them. Obtained (Mitsuba 3 Python package) with
/// `mi.traverse(mi.load_dict({'type': 'conductor', 'material': NAME}))` and
/// reading `eta.value` / `k.value` (the spectral data in `data/ior/*.spd`
/// converted by Mitsuba to sRGB). `none` is Mitsuba's default: eta 0, k 1
/// (a perfect mirror). Mitsuba has no plain "Ni" (only "Ni_palik"); "Ni" is
/// accepted here as an alias for it.
#[allow(clippy::excessive_precision)]
const CONDUCTORS: &[(&str, [f32; 3], [f32; 3])] = &[
    ("none", [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]),
    (
        "Au",
        [0.143_036, 0.375_307, 1.442_045],
        [3.982_997, 2.385_556, 1.603_359],
    ),
    (
        "Ag",
        [0.155_276, 0.116_728, 0.138_388],
        [4.828_354, 3.122_222, 2.146_901],
    ),
    (
        "Al",
        [1.657_501, 0.880_405, 0.521_244],
        [9.223_811, 6.269_502, 4.837_004],
    ),
    (
        "Cu",
        [0.201_005, 0.923_750, 1.102_215],
        [3.913_262, 2.453_045, 2.142_090],
    ),
    (
        "Cr",
        [4.369_668, 2.916_505, 1.654_905],
        [5.206_547, 4.231_306, 3.754_699],
    ),
    (
        "W",
        [4.370_817, 3.300_246, 2.998_407],
        [3.500_641, 2.604_874, 2.273_233],
    ),
    (
        "Ni_palik",
        [2.367_305, 1.663_373, 1.467_078],
        [4.498_812, 3.050_153, 2.345_439],
    ),
    (
        "Ni",
        [2.367_305, 1.663_373, 1.467_078],
        [4.498_812, 3.050_153, 2.345_439],
    ),
    (
        "Hg",
        [2.398_939, 1.440_028, 0.909_570],
        [6.327_587, 4.371_925, 3.421_764],
    ),
    (
        "a-C",
        [2.944_046, 2.227_136, 1.968_162],
        [0.887_465, 0.799_299, 0.815_290],
    ),
    (
        "Be",
        [4.185_012, 3.185_029, 2.784_061],
        [3.835_466, 3.010_122, 2.868_994],
    ),
    (
        "Ir",
        [3.086_300, 2.082_191, 1.617_915],
        [5.592_153, 4.067_088, 3.267_312],
    ),
    (
        "K",
        [0.064_043, 0.046_410, 0.038_185],
        [2.104_200, 1.348_940, 0.913_126],
    ),
    (
        "Li",
        [0.265_791, 0.195_618, 0.220_949],
        [3.540_155, 2.311_123, 1.668_607],
    ),
    (
        "Mo",
        [4.483_974, 3.525_131, 2.776_310],
        [4.111_437, 3.420_827, 3.150_607],
    ),
    (
        "Na_palik",
        [0.060_269, 0.056_141, 0.061_988],
        [3.179_273, 2.112_490, 1.579_041],
    ),
    (
        "Nb",
        [3.420_074, 2.790_093, 2.395_629],
        [3.441_395, 2.737_666, 2.579_746],
    ),
    (
        "Rh",
        [2.585_793, 1.860_216, 1.554_263],
        [6.782_260, 4.702_987, 3.976_073],
    ),
    (
        "Ta",
        [2.062_721, 2.392_939, 2.627_929],
        [2.408_360, 1.741_486, 1.947_028],
    ),
    (
        "TiN",
        [1.648_450, 1.150_516, 1.379_823],
        [3.368_328, 1.943_498, 1.102_068],
    ),
    (
        "V_palik",
        [4.277_582, 3.512_949, 2.761_071],
        [3.491_301, 2.889_455, 3.111_522],
    ),
    (
        "VN",
        [2.865_602, 2.119_189, 1.940_091],
        [3.032_243, 2.056_116, 1.616_306],
    ),
];

/// Look up a named conductor (case-sensitive, as Mitsuba's file names are).
pub(crate) fn lookup_conductor(name: &str) -> Result<(Vec3, Vec3), String> {
    CONDUCTORS
        .iter()
        .find(|(n, _, _)| *n == name)
        .map(|(_, eta, k)| (Vec3::from_array(*eta), Vec3::from_array(*k)))
        .ok_or_else(|| {
            let names: Vec<&str> = CONDUCTORS.iter().map(|(n, _, _)| *n).collect();
            format!(
                "unknown conductor material \"{name}\"; supported: {}",
                names.join(", ")
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn named_iors_match_mitsuba_table_case_insensitively() {
        assert_eq!(lookup_ior("BK7").unwrap(), 1.5046);
        assert_eq!(lookup_ior("water").unwrap(), 1.3330);
        assert_eq!(lookup_ior("air").unwrap(), 1.000277);
        assert!(lookup_ior("unobtainium").unwrap_err().contains("bk7"));
    }

    #[test]
    fn gold_conductor_has_mitsuba_rgb_values() {
        let (eta, k) = lookup_conductor("Au").unwrap();
        assert!((eta.x - 0.143036).abs() < 1e-5 && (k.z - 1.603359).abs() < 1e-5);
        assert_eq!(lookup_conductor("none").unwrap(), (Vec3::ZERO, Vec3::ONE));
        assert!(lookup_conductor("Unobtainium").is_err());
    }
}
