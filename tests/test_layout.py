from stgc.model.layout import bytes_per_gaussian, ply_fields


def test_official_row_sizes_match_the_paper_convention():
    # The paper's sizes are #Gaussians x 152 B (433,936 x 152 B = 62.9 MiB).
    assert bytes_per_gaussian("full") == 152
    assert bytes_per_gaussian("full", include_normals=False) == 140
    assert bytes_per_gaussian("lite") == 128
    assert round(433_936 * bytes_per_gaussian("full") / 2**20, 1) == 62.9
    assert ply_fields("full")[:5] == ["x", "y", "z", "trbf_center", "trbf_scale"]
    assert ply_fields("full")[-3:] == ["f_t_0", "f_t_1", "f_t_2"]
