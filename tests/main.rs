//! pathfarm's one integration-test binary. Each module tests one behaviour
//! area through the public APIs and the real `pathfarm` executable.

mod common;

mod it {
    pub mod analytic;
    pub mod bad_input;
    pub mod converge;
    pub mod crosscheck;
    pub mod dashboard;
    pub mod determinism;
    pub mod farm;
    pub mod farm_sim;
    pub mod guide_cli;
    pub mod guided;
    pub mod hostile;
    pub mod outputs;
    pub mod session;
    pub mod shared_scenes;
    pub mod stability;
    pub mod surface_detail;
}
