"""skidbench.pipeline.splits"""
