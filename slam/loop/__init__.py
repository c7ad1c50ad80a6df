"""Loop closure: ORB bag-of-words place recognition, keyframe database, geometric verification.

Submodules are imported explicitly (``from slam.loop.vocabulary import Vocabulary``); this
package imports nothing heavy on its own.
"""
