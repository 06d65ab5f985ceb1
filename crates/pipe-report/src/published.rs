//! Published reference figures, for orientation only: numbers from papers, measured by their
//! authors on their own renders of the scenes, not by this tool and not on the data of a report.

use serde::Serialize;

/// One row: a scene and each method's published test-view PSNR (dB).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PublishedRow {
    /// PAC-NeRF scene.
    pub scene: &'static str,
    /// PAC-NeRF's test-view PSNR, dB.
    pub pac_nerf_db: f64,
    /// The seed method's test-view PSNR, dB.
    pub seed_method_db: f64,
}

/// The seed paper's Table 1 (test-view PSNR on the PAC-NeRF scenes it reports).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Published {
    /// Where the numbers come from.
    pub source: &'static str,
    /// What they are and are not.
    pub note: &'static str,
    /// The rows.
    pub rows: Vec<PublishedRow>,
}

/// The figures.
pub fn table1() -> Published {
    Published {
        source: "seed paper, Table 1",
        note: "Published numbers on other data (the authors' own renders and splits), for orientation; not measured by pipe and not comparable one to one with the scores above.",
        rows: vec![
            PublishedRow {
                scene: "droplet",
                pac_nerf_db: 32.93,
                seed_method_db: 21.84,
            },
            PublishedRow {
                scene: "cream",
                pac_nerf_db: 35.87,
                seed_method_db: 24.88,
            },
            PublishedRow {
                scene: "torus",
                pac_nerf_db: 32.86,
                seed_method_db: 19.90,
            },
            PublishedRow {
                scene: "cat",
                pac_nerf_db: 32.60,
                seed_method_db: 28.91,
            },
        ],
    }
}
