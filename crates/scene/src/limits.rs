//! The limits on what a scene file or a flag may make pathfarm allocate or compute, and on
//! which files a scene may read ([`Limits::confine_files`]).
//!
//! A scene is untrusted input (the farm takes it from the network), so every number that turns
//! into memory or work is checked against these limits *before* anything is allocated, with an
//! error that names the file and line (or the flag), the value and the limit. They are kept in
//! one place so that a deployment can set its own; the defaults admit real production scenes
//! (16k x 16k films, meshes of hundreds of millions of triangles where memory allows).

/// Resource limits on untrusted input. `Limits::default()` documents each default.
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    /// Largest scene XML file, in bytes, with the files it includes counted together
    /// (default 256 MiB).
    pub max_scene_file_bytes: u64,
    /// Deepest nesting of `<include>` (default 16).
    pub max_include_depth: usize,
    /// Most files a scene may include, all told (default 1024).
    pub max_include_files: usize,
    /// Deepest nesting of XML elements in a scene file (default 100; real scenes nest fewer
    /// than 10 deep). Checked before the XML is parsed, so deep nesting cannot exhaust the
    /// stack.
    pub max_xml_depth: usize,
    /// Total text that `$name` substitution may produce in one scene file, in bytes
    /// (default 16 MiB): `<default>` values that expand each other cannot grow exponentially.
    pub max_substituted_bytes: usize,
    /// Film width and height, each (default 16384).
    pub max_film_side: u32,
    /// Film pixels, width x height (default 16384 x 16384).
    pub max_film_pixels: u64,
    /// Reconstruction filter radius, in pixels (default 16; Mitsuba's filters reach 1-2).
    /// A pixel gathers samples from (2 radius + 1)^2 pixels.
    pub max_filter_radius: f64,
    /// Samples per pixel of a render, flags and scene alike (default 2^24).
    pub max_spp: u64,
    /// A time budget, in seconds (default one week, 604800).
    pub max_time_seconds: f64,
    /// Triangles of one mesh (default 2^31; indices are 32-bit).
    pub max_mesh_triangles: u64,
    /// Vertices of one mesh (default 2^31).
    pub max_mesh_vertices: u64,
    /// Vertices of one polygon of an OBJ or PLY face (default 2^20).
    pub max_polygon_vertices: u64,
    /// Pixels of one texture or environment map (default 16384 x 16384 x 4, e.g. a 32k x 16k
    /// environment map).
    pub max_texture_pixels: u64,
    /// Pixels of a picture a command draws (`pathfarm guide show` / `scatter`; default
    /// 8192 x 8192).
    pub max_picture_pixels: u64,
    /// Directions `pathfarm guide scatter` draws per strategy (default 2^26).
    pub max_scatter_samples: u64,
    /// Memory the scene's data and the render may take, in bytes, estimated before they are
    /// allocated (default: the machine's physical memory; 16 GiB where it cannot be read).
    pub max_memory_bytes: u64,
    /// Memory of a path-guiding SD-tree, in bytes, unless the scene's `max_memory_mb` asks for
    /// less (default: a quarter of `max_memory_bytes`). Refinement coarsens the quadtrees
    /// rather than exceed it.
    pub max_guide_memory_bytes: u64,
    /// Confine the files a scene reads to its own directory (default false: a local user's
    /// scene may name absolute paths and `..`, and `pathfarm render` allows them). When true,
    /// as for a scene bundle the farm takes from the network, every file name a scene gives
    /// (meshes, textures, environment maps) must be relative, without `..` components, and
    /// resolve, symbolic links followed, to a file inside the directory of the scene file;
    /// anything else is an error naming the scene file, the line and the file name. (The
    /// files are then read through the names as written, so the directory must not change
    /// while the scene loads.)
    pub confine_files: bool,
}

impl Default for Limits {
    fn default() -> Self {
        let memory = physical_memory_bytes().unwrap_or(16 << 30);
        Self {
            max_scene_file_bytes: 256 << 20,
            max_include_depth: 16,
            max_include_files: 1024,
            max_xml_depth: 100,
            max_substituted_bytes: 16 << 20,
            max_film_side: 16384,
            max_film_pixels: 16384 * 16384,
            max_filter_radius: 16.0,
            max_spp: 1 << 24,
            max_time_seconds: 604_800.0,
            max_mesh_triangles: 1 << 31,
            max_mesh_vertices: 1 << 31,
            max_polygon_vertices: 1 << 20,
            max_texture_pixels: 16384 * 16384 * 4,
            max_picture_pixels: 8192 * 8192,
            max_scatter_samples: 1 << 26,
            max_memory_bytes: memory,
            max_guide_memory_bytes: memory / 4,
            confine_files: false,
        }
    }
}

/// `MemTotal` of `/proc/meminfo`, where there is one.
fn physical_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// A byte count for messages: "25.8 GB (25769803776 bytes)".
pub fn format_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    let (v, unit) = if b >= 1e9 {
        (b / 1e9, "GB")
    } else if b >= 1e6 {
        (b / 1e6, "MB")
    } else if b >= 1e3 {
        (b / 1e3, "kB")
    } else {
        return format!("{bytes} bytes");
    };
    format!("{v:.1} {unit} ({bytes} bytes)")
}

/// A number for a message: plain when short ("0.5", "604800"), else in scientific notation
/// ("1e-5", "1e300"), never hundreds of digits.
pub fn format_number(x: f64) -> String {
    let plain = format!("{x}");
    if plain.len() <= 6 {
        plain
    } else {
        format!("{x:e}")
    }
}
