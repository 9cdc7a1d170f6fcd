"""One pair of fragments: segmentation into fracture and skin, contours and their features,
feature fusion, the LCS, point-pair features, ICP and verification, and `prepare`/`match_pair`."""
