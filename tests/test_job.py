"""fmapping.job.Job: the command line as one typed object (the library never sees argparse)."""
import pytest


def test_job_from_the_cli_arguments_and_its_mapper_settings():
    from fmapping.cli import build_parser
    from fmapping.job import Job
    from fmapping.mapping import MapperConfig

    a = build_parser().parse_args(["slam", "--data", "d", "--out", "o", "--use-depth", "--device", "cpu",
                                   "--bbox=-1,-2,-3,1,2,3", "--no-export", "--data-fps", "12.5", "--field", "vm"])
    job = Job.from_args(a, poses="photometric")
    assert (job.data, job.out, job.poses, job.use_depth, job.export, job.data_fps) == ("d", "o", "photometric",
                                                                                       True, False, 12.5)
    assert job.bbox == ((-1.0, -2.0, -3.0), (1.0, 2.0, 3.0)) and job.source_options() == {"fps": 12.5, "topic": None}
    cfg = job.mapper_config(MapperConfig())
    assert cfg.use_depth and cfg.bbox == job.bbox and cfg.device == "cpu"
    assert cfg.field.kind == "vm" and cfg.field.resolution == MapperConfig().field.resolution  # only the kind
    # fmapping slam's whole config carries it to its mapper
    from fmapping.slam.config import build_slam_config

    assert build_slam_config(job).mapper.field.kind == "vm"
    # defaults where the namespace has nothing: the map command's pose source, export on, the config's device
    m = Job.from_args(build_parser().parse_args(["map", "--data", "d", "--out", "o"]), poses="gt")
    assert m.poses == "gt" and m.export and m.mapper_config(MapperConfig()) == MapperConfig()
    with pytest.raises(TypeError):
        Job.from_args(build_parser().parse_args(["map", "--data", "d", "--out", "o"]), bogus=1)
