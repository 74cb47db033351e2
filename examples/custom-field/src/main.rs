//! `nerf-plenoxels`: the whole `nerf` command line with one more field, `plenoxels`
//! (`nerf-plenoxels train SCENE --field plenoxels`).

fn main() {
    let mut registry = nerf::registry();
    registry.register(nerf_plenoxels::registry_entry());
    nerf_cli::main_with(&registry);
}
