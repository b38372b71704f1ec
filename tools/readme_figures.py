"""Draw the pictures of the simulator in docs/ (``python tools/readme_figures.py``).

Writes docs/simulated_street.png (top view of the mapped campaign of the default street,
coloured by class), docs/simulated_facade.png (one façade in its own frame, coloured
by depth: recesses, balconies, an oriel, columns and the shadow of a tree) and
docs/facade_model.png (the model of that façade: mean depth and standard deviation, drawn
by uncertain_facade_map_apps.plots, which also draws the full per-façade figures of
``uncertain-facade-map plot``).
"""

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from uncertain_facade_map.io.cloud import CLASS_NAMES  # noqa: E402
from uncertain_facade_map.simulation.campaign import simulate_campaign  # noqa: E402
from uncertain_facade_map.simulation.scenes import build_scene  # noqa: E402
from uncertain_facade_map_apps.plots import draw_surface  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / 'docs'
COLOURS = {0: '#999999', 1: '#d62728', 2: '#c7c7c7', 3: '#2ca02c', 4: '#1f77b4', 5: '#ff7f0e'}


def main() -> None:
    DOCS.mkdir(exist_ok=True)
    scene = build_scene('street', 0)
    cloud = simulate_campaign(scene, 0)
    pts = cloud.points
    rng = np.random.default_rng(0)
    sub = pts[rng.random(len(pts)) < 0.15]

    fig, ax = plt.subplots(figsize=(12, 3.6))
    for label, colour in COLOURS.items():
        m = sub['class'] == label
        if m.any():
            ax.scatter(sub['x'][m], sub['y'][m], s=0.05, c=colour, label=CLASS_NAMES[label], rasterized=True)
    o = cloud.sensor_origins
    ax.plot(o[::500, 0], o[::500, 1], 'k-', lw=1, label='trajectory')
    ax.set_aspect('equal')
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_title(f'street scene, campaign 0: {len(pts):,} points (map frame, top view)')
    ax.legend(markerscale=40, loc='upper right', fontsize=7, ncol=7)
    fig.tight_layout()
    fig.savefig(DOCS / 'simulated_street.png', dpi=110)
    plt.close(fig)

    facade = scene.facades[0]
    m = pts['gt_facade'] == facade.facade_id
    uvn = facade.frame.to_facade(np.stack([pts['x'][m], pts['y'][m], pts['z'][m]], axis=1))
    fig, axs = plt.subplots(1, 2, figsize=(12, 4.2), gridspec_kw={'width_ratios': [3, 1]})
    sc = axs[0].scatter(uvn[:, 0], uvn[:, 1], c=uvn[:, 2], s=0.2, cmap='coolwarm', vmin=-0.3, vmax=1.5,
                        rasterized=True)
    axs[0].set_aspect('equal')
    axs[0].set_xlabel('u along the façade [m]')
    axs[0].set_ylabel('v up [m]')
    axs[0].set_title(f'façade {facade.facade_id}: {m.sum():,} returns, coloured by depth')
    fig.colorbar(sc, ax=axs[0], label='depth n out of the wall [m]')
    axs[1].scatter(uvn[:, 2], uvn[:, 1], s=0.1, c='k', alpha=0.3, rasterized=True)
    axs[1].set_xlabel('depth n [m]')
    axs[1].set_title('side view (profile)')
    axs[1].set_xlim(-0.6, 2.0)
    fig.tight_layout()
    fig.savefig(DOCS / 'simulated_facade.png', dpi=110)
    plt.close(fig)
    draw_model(cloud, facade)
    print(f'wrote {DOCS}/simulated_street.png, simulated_facade.png and facade_model.png')


def draw_model(cloud, truth_facade) -> None:
    """Map the first building of the street and draw its street façade's mean and std."""
    from uncertain_facade_map.mapping.facade_map import build_map

    pts = cloud.points[(cloud.points['class'] == 1) & (cloud.points['building_id'] == truth_facade.building_id)]
    fmap = build_map(np.stack([pts['x'], pts['y'], pts['z']], 1), pts['building_id'],
                     np.stack([pts['origin_x'], pts['origin_y'], pts['origin_z']], 1))
    model = min(fmap.facades, key=lambda f: np.linalg.norm(f.frame.normal - truth_facade.frame.n))
    fig, axs = plt.subplots(2, 1, figsize=(11, 9))
    draw_surface(axs[0], model, 'mean', vmin=-0.3, vmax=1.5)
    axs[0].set_title(f'façade model: mean surface depth ({model.layers.n_layers} GMM layers, '
                     f'{model.facets.n_facets} facets)')
    draw_surface(axs[1], model, 'std', vmin=0, vmax=30, unit='cm')
    axs[1].set_title('standard deviation of the surface (occluded and unscanned parts high)')
    fig.tight_layout()
    fig.savefig(DOCS / 'facade_model.png', dpi=100)
    plt.close(fig)


if __name__ == '__main__':
    main()
