"""The long-running processes: a mapper shard (mapper), a SLAM node (slam_node), a source (source), the Zenoh
router (router) and `posegrid run`'s launcher (launcher). Each wraps network-free state (services.state) in Zenoh
declarations; none imports the command-line modules."""
