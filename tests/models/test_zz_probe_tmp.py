from driftlab.models.fitting import FitOptions, fit_bundles
from tests.models.test_fitting import synthetic_bundle

def test_probe_features():
    r = fit_bundles([synthetic_bundle(0)], FitOptions(network=False))
    print("\nPROBE", [f.name for f in r.models[("T1", "dz")].features])
