//! `nerf`: train and evaluate radiance fields from the command line: [`nerf_cli::main_with`] and
//! the fields nerf-rs ships ([`nerf::registry`]).

fn main() {
    nerf_cli::main_with(&nerf::registry());
}
