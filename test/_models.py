"""Model directory helpers shared by several test modules (no test module imports another)."""
import json

import numpy as np

from beo_ros.core.bank import _sha256


def save_with_classifier(bank, classifier, path):
    """Save ``bank`` to ``path`` with ``classifier`` (mode -> arrays) as its classifier.npz and
    a manifest that lists it: a directory ``ModelBank.load`` checks, with a classifier that the
    ``ModelBank`` constructor refuses. Returns ``path``."""
    path = bank.save(path)
    np.savez_compressed(path / 'classifier.npz', **{
        f'{mode}__{k}': np.asarray(v) for mode, clf in classifier.items() for k, v in clf.items()})
    manifest = json.loads((path / 'manifest.json').read_text())
    manifest['files']['classifier.npz'] = _sha256(path / 'classifier.npz')
    (path / 'manifest.json').write_text(json.dumps(manifest))
    return path
