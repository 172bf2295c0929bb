"""Object masks for photos that come without them (`wgs prepare --masks auto`).

Three steps, each its own module: a salient-object network proposes a soft mask per photo
(`saliency`); the posed views vote, so that a pixel whose ray misses the hull of what the other
views call object becomes background (`agreement`); edges follow the photo and specks and small
holes go (`refine`). `automask` runs them in that order.
"""
